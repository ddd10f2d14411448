"""Tests of simulator/: the emulated module on the wire, the mechanism, the pytest plugin."""
