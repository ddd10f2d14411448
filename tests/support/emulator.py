"""The emulated LDQ-412 for tests: in this process on a technician-moved shoulder joint
(:func:`hand_emulator`), the recorded scans checked against what it really made, and the
wire tests' constants and oracle."""

from __future__ import annotations

import socket

import numpy as np
import serial

from loopcal.calibration.parameters import NOMINAL
from loopcal.simulator import Emulator
from loopcal.simulator.clock import Clock, HeldClock
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.mechanism import MechanismSource
from loopcal.simulator.motion import Scenario
from loopcal.simulator.open_points import OpenPoints
from loopcal.simulator.scenarios import HandMoves
from loopcal.simulator.source import ConstantSource

SILENCE_S = 0.15  # well above the datasheet's 10 ms answer time
#: s, the longest an answer is waited for: the module answers from the test's process,
#: which a loaded machine held past SILENCE_S once (an answer cut after its first byte)
ANSWER_S = 2.0


def ascii_ask(port: serial.Serial, frame: bytes, wait: float = ANSWER_S) -> bytes:
    """Send one ASCII frame to an emulated module; its answer up to and including the CR,
    or b"" when no byte comes within ``wait`` s (SILENCE_S where a test expects none). An
    answer begun is read to its CR, for up to :data:`ANSWER_S`."""
    port.reset_input_buffer()
    port.timeout = wait
    try:
        port.write(frame)
        first = port.read(1)
        if first in (b"", b"\r"):
            return first
        port.timeout = ANSWER_S
        return first + port.read_until(b"\r")
    finally:
        port.timeout = wait


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


def hand_emulator(
    transport: str = "modbus-tcp",
    *,
    rate: int = 20,
    speed: float = 1.0,
    seed: int = 0,
    drifts: tuple[OffsetDrift, ...] = (),
    clock: Clock | None = None,
    open_points: OpenPoints | None = None,
    motion: Scenario | None = None,
    line: str = "pty",
) -> Emulator:
    """An emulated LDQ-412 on a technician-moved shoulder joint (not started), whose clock
    (``speed`` times wall time) starts at the recorder's first request: however long the
    recorder subprocess takes to start on a busy machine, the FIFO (1.28 s deep at 200 Hz)
    does not overflow before it connects. ``clock``: another clock instead (``speed`` is
    then not used); ``open_points``: the emulator's settings for what the datasheet leaves
    open; ``motion``: another scenario than the technician's hand (a task loop); ``line``:
    a serial transport's line (tests.support.drivers.tcp_line)."""
    if clock is None:
        clock = HeldClock(speed)  # the emulator starts it at the first request
    source = MechanismSource(motion or HandMoves(seed), NOMINAL, noise_volts=0.04, seed=seed,
                             drifts=drifts)  # fmt: skip
    return Emulator(transport, source, scan_rate_hz=rate, clock=clock, seed=seed,
                    open_points=open_points, line=line)  # fmt: skip


def truth_table(emu: Emulator) -> dict[tuple[int, int], tuple[int, tuple[int, ...]]]:
    """(boot, counter) -> (time_us, codes) of every scan the emulated module made."""
    return {(s.boot, s.counter): (s.time_us, s.codes) for s in emu.truth}


def assert_matches_truth(rows: np.ndarray, emu: Emulator, *, boot_of_epoch=lambda e: e) -> None:
    """Every recorded scan is the module's scan with that counter, bit for bit."""
    truth = truth_table(emu)
    for r in rows:
        key = (boot_of_epoch(int(r["epoch"])), int(r["counter64"]) & 0xFFFFFFFF)
        assert key in truth, f"recorded scan {key} never happened"
        t_us, codes = truth[key]
        assert (int(r["time64_us"]) & 0xFFFFFFFF) == t_us, key
        assert tuple(int(c) for c in r["codes"]) == codes, key
