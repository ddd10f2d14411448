"""Tests of daemon/commands/ and the command line's conventions."""
