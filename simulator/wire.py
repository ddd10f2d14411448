"""Wire-level fault state shared by the servers, and how each protocol gets corrupted.

The servers consult :class:`WireFaults` (under the emulator's lock) before they answer:
``disconnected`` (the link carries nothing), a stall (the module ignores requests until a
device-clock deadline), pending garbage (junk bytes sent just before the next answer) and
pending corruption (the next n answers break their CRC, checksum or MBAP header).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .open_points import Latency

Corrupter = Callable[[bytes], bytes]


@dataclass
class WireFaults:
    """Mutable wire fault state. ``rng`` draws the garbage bytes (seeded: reproducible).

    latency: how long answers take (None: sent at once); ``latency_rng`` draws the delays.
    """

    rng: np.random.Generator
    latency_rng: np.random.Generator
    latency: Latency | None = None
    disconnected: bool = False
    stalled_until_ns: int | None = None
    garbage: bytes = b""
    corrupt: int = 0
    answers_sent: int = 0  # answers that went out (diagnostics)

    def stalled(self, now_ns: int) -> bool:
        """True while a stall lasts (device-clock time)."""
        if self.stalled_until_ns is not None and now_ns >= self.stalled_until_ns:
            self.stalled_until_ns = None
        return self.stalled_until_ns is not None

    def delay_s(self, transport: str) -> float:
        """How long the answer being sent now waits, s (0 without latency)."""
        if self.latency is None:
            return 0.0
        return self.latency.draw_s(self.latency_rng, transport)

    def add_garbage(self, nbytes: int) -> None:
        """Queue ``nbytes`` random bytes to go out just before the next answer."""
        if nbytes < 0:
            raise ValueError("nbytes must be >= 0")
        self.garbage += self.rng.integers(0, 256, nbytes, dtype=np.uint8).tobytes()

    def outgoing(self, answer: bytes, corrupter: Corrupter) -> bytes:
        """The bytes to put on the wire for ``answer``, pending faults applied."""
        if self.corrupt > 0:
            self.corrupt -= 1
            answer = corrupter(answer)
        out, self.garbage = self.garbage + answer, b""
        self.answers_sent += 1
        return out

    def clear(self) -> None:
        """Forget pending garbage, corruption and any stall (not the link state)."""
        self.stalled_until_ns = None
        self.garbage = b""
        self.corrupt = 0


def corrupt_rtu(frame: bytes) -> bytes:
    """Break the CRC of a Modbus RTU frame (its last byte inverted)."""
    return frame[:-1] + bytes([frame[-1] ^ 0xFF])


def corrupt_mbap(frame: bytes) -> bytes:
    """Break the MBAP header of a Modbus TCP frame: protocol identifier 0 becomes 1."""
    return frame[:2] + bytes([frame[2], frame[3] ^ 0x01]) + frame[4:]


def corrupt_ascii(checksum: bool) -> Corrupter:
    """Break an ASCII answer (``body [cs] CR``).

    With checksum mode on, the two checksum digits become those of sum + 1 (still hex,
    wrong value). Without it, the byte after the lead character gets bit 6 flipped, which
    turns a hex digit into a non-hex character (``0`` -> ``p``, ``A`` -> 0x01).
    """

    def corrupter(frame: bytes) -> bytes:
        if checksum and len(frame) >= 3:
            wrong = (int(frame[-3:-1], 16) + 1) & 0xFF
            return frame[:-3] + b"%02X" % wrong + frame[-1:]
        if len(frame) >= 3:
            return frame[:1] + bytes([frame[1] ^ 0x40]) + frame[2:]
        return frame

    return corrupter
