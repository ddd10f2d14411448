"""Tests of daemon/recorder/: acquisition, the daemon, polling, stamps, metrics, replay
round trips."""
