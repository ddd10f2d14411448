"""Helpers shared by the emulator's wire tests."""

from __future__ import annotations

import socket

from loopcal.simulator.source import ConstantSource

SILENCE_S = 0.15  # well above the datasheet's 10 ms answer time
GOLDEN_CODES = (2048, 1, 4095, 3000)  # the datasheet's ASCII example


def mid_volts(code: int) -> float:
    """The datasheet's mid-code reconstruction, restated here as the tests' own oracle."""
    return (code + 0.5) * 20.0 / 4096 - 10.0


def golden_source() -> ConstantSource:
    """Constant inputs that convert to the datasheet example's codes."""
    return ConstantSource([mid_volts(c) for c in GOLDEN_CODES])


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Exactly n bytes from a socket, or ConnectionError if it closes first."""
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data
