"""Tests of systemd/: the units."""
