"""Tests of drivers/: the three transports against the emulator, scripted wires and an
independent module."""
