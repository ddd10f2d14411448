"""Tests of daemon/live/: loop-closure health and live guidance."""
