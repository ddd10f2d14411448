"""Tests of daemon/worker/: poses, gates, calibrate, write-back, the report."""
