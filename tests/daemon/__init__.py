"""Tests of daemon/, one folder per sub-package; the parsers' fuzzers here."""
