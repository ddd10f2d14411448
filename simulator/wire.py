"""Wire-level fault state shared by the servers, and how each protocol gets corrupted.

The servers consult :class:`WireFaults` (under the emulator's lock) before they answer:
``disconnected`` (the link carries nothing), a stall (the module ignores requests until a
device-clock deadline), pending garbage (junk bytes sent just before the next answer) and
pending corruption (the next n answers break their CRC, checksum or MBAP header).

A serial line set to two different rates corrupts every byte: :func:`uart_receive` is what
a UART at one rate makes of bytes sent at another (the pty link applies it,
:mod:`loopcal.simulator.pty`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .open_points import Latency

Corrupter = Callable[[bytes], bytes]


def check_not_negative(name: str, value: float) -> None:
    """Refuse a negative count or duration of a fault.

    Parameters
    ----------
    name : str
        The argument's name, for the message.
    value : float
        Its value.

    Raises
    ------
    ValueError
        ``NAME must be >= 0`` if ``value`` is negative.
    """
    if value < 0:
        raise ValueError(f"{name} must be >= 0")


@dataclass
class WireFaults:
    """Mutable wire fault state, consulted by the servers under the emulator's lock.

    Attributes
    ----------
    rng : numpy.random.Generator
        Draws the garbage bytes (seeded: reproducible).
    latency_rng : numpy.random.Generator
        Draws the answer delays.
    latency : Latency or None, default None
        How long answers take (None: sent at once).
    disconnected : bool, default False
        The link carries nothing.
    stalled_until_ns : int or None, default None
        The module ignores requests until this device-clock time, ns (None: no stall).
    garbage : bytes, default b""
        Junk bytes to go out just before the next answer.
    corrupt : int, default 0
        How many of the next answers to break.
    answers_sent : int, default 0
        Answers that went out (diagnostics).
    bytes_sent : int, default 0
        Their bytes, garbage included (diagnostics: a test reads until it has them all).
    """

    rng: np.random.Generator
    latency_rng: np.random.Generator
    latency: Latency | None = None
    disconnected: bool = False
    stalled_until_ns: int | None = None
    garbage: bytes = b""
    corrupt: int = 0
    answers_sent: int = 0  # answers that went out (diagnostics)
    bytes_sent: int = 0

    def stalled(self, now_ns: int) -> bool:
        """Whether a stall lasts at ``now_ns``; an expired stall is forgotten.

        Parameters
        ----------
        now_ns : int
            Device-clock time, ns.

        Returns
        -------
        bool
            True while ``now_ns`` is before :attr:`stalled_until_ns`.
        """
        if self.stalled_until_ns is not None and now_ns >= self.stalled_until_ns:
            self.stalled_until_ns = None
        return self.stalled_until_ns is not None

    def delay_s(self, transport: str) -> float:
        """How long the answer being sent now waits.

        Parameters
        ----------
        transport : str
            ``"modbus-tcp"``, ``"modbus-rtu"`` or ``"ascii"`` (the datasheet's bound
            differs).

        Returns
        -------
        float
            The delay, s; 0.0 without a latency (then nothing is drawn).
        """
        if self.latency is None:
            return 0.0
        return self.latency.draw_s(self.latency_rng, transport)

    def add_garbage(self, nbytes: int) -> None:
        """Queue ``nbytes`` random bytes to go out just before the next answer.

        Parameters
        ----------
        nbytes : int
            How many, >= 0.

        Raises
        ------
        ValueError
            If ``nbytes`` is negative.
        """
        check_not_negative("nbytes", nbytes)
        self.garbage += self.rng.integers(0, 256, nbytes, dtype=np.uint8).tobytes()

    def outgoing(self, answer: bytes, corrupter: Corrupter) -> bytes:
        """The bytes to put on the wire for ``answer``, pending faults applied.

        Uses up one pending corruption and all pending garbage, and counts the answer.

        Parameters
        ----------
        answer : bytes
            The complete frame the protocol would send.
        corrupter : callable
            ``corrupter(frame) -> bytes`` breaks a frame of this protocol
            (:func:`corrupt_rtu`, :func:`corrupt_mbap`, :func:`corrupt_ascii`).

        Returns
        -------
        bytes
            The pending garbage, then the answer (broken if a corruption was pending).
        """
        if self.corrupt > 0:
            self.corrupt -= 1
            answer = corrupter(answer)
        out, self.garbage = self.garbage + answer, b""
        self.answers_sent += 1
        self.bytes_sent += len(out)
        return out

    def clear(self) -> None:
        """Forget pending garbage, corruption and any stall (not the link, nor the latency)."""
        self.stalled_until_ns = None
        self.garbage = b""
        self.corrupt = 0


def corrupt_rtu(frame: bytes) -> bytes:
    """Break the CRC of a Modbus RTU frame (its last byte inverted).

    Parameters
    ----------
    frame : bytes
        A complete RTU frame, CRC included (at least one byte).

    Returns
    -------
    bytes
        The frame with its last byte XOR 0xFF.
    """
    return frame[:-1] + bytes([frame[-1] ^ 0xFF])


def corrupt_mbap(frame: bytes) -> bytes:
    """Break the MBAP header of a Modbus TCP frame: protocol identifier 0 becomes 1.

    Parameters
    ----------
    frame : bytes
        A complete Modbus TCP frame (at least the MBAP's first four bytes).

    Returns
    -------
    bytes
        The frame with byte 3 (the protocol identifier's low byte) XOR 0x01.
    """
    return frame[:2] + bytes([frame[2], frame[3] ^ 0x01]) + frame[4:]


def corrupt_ascii(checksum: bool) -> Corrupter:
    """A corrupter of ASCII answers (``body [cs] CR``) for a checksum mode.

    With checksum mode on, the two checksum digits become those of sum + 1 (still hex,
    wrong value). Without it, the byte after the lead character gets bit 6 flipped, which
    turns a hex digit into a non-hex character (``0`` -> ``p``, ``A`` -> 0x01).

    Parameters
    ----------
    checksum : bool
        The module's ASCII checksum mode when the answer is made.

    Returns
    -------
    callable
        ``corrupter(frame) -> bytes``; a frame shorter than three bytes comes back
        unchanged.
    """

    def corrupter(frame: bytes) -> bytes:
        if checksum and len(frame) >= 3:
            wrong = (int(frame[-3:-1], 16) + 1) & 0xFF
            return frame[:-3] + b"%02X" % wrong + frame[-1:]
        if len(frame) >= 3:
            return frame[:1] + bytes([frame[1] ^ 0x40]) + frame[2:]
        return frame

    return corrupter


#: data bits of a character on the module's serial lines (8N1: one start bit, 8 data bits
#: least significant first, no parity, one stop bit)
DATA_BITS = 8
#: the line's levels of one 8N1 character: start (0), data, stop (1)
_FRAME_BITS = 1 + DATA_BITS + 1


def uart_receive(data: bytes, sent_baud: int, heard_baud: int) -> bytes:
    """What a UART listening at ``heard_baud`` receives when ``data`` is sent back to back at
    ``sent_baud``, both 8N1: the bytes a host or a module at the wrong rate reads.

    The receiver waits for a falling edge (a start bit), samples the line in the middle of
    each of its own bit times (start, 8 data bits, stop), and looks for the next falling
    edge after the stop bit's sample. A character whose start bit is high again at its
    middle is a glitch and gives nothing; one whose stop bit is low is a framing error and
    reads as a NUL byte, as Linux delivers it to a raw port (no ``IGNPAR``, no
    ``PARMRK``). At equal rates the bytes come through unchanged.

    Parameters
    ----------
    data : bytes
        What the sender wrote, as one burst (the line idle, high, before and after).
    sent_baud, heard_baud : int
        The two ends' line rates, baud (> 0).

    Returns
    -------
    bytes
        What the receiver reads: at another rate, garbage (often NUL bytes, more or fewer
        of them than were sent), never a valid frame but by chance.

    Raises
    ------
    ValueError
        If a rate is not > 0.
    """
    if sent_baud <= 0 or heard_baud <= 0:
        raise ValueError(f"baud rates must be > 0, got {sent_baud} and {heard_baud}")
    if sent_baud == heard_baud or not data:
        return data
    line = []  # the line's level in each of the sender's bit times
    for byte in data:
        line += [0, *((byte >> i) & 1 for i in range(DATA_BITS)), 1]
    n = len(line)
    r = sent_baud / heard_baud  # one of the receiver's bit times, in the sender's

    def level(t: float) -> int:
        i = int(t)
        return line[i] if i < n else 1

    out = bytearray()
    i = 0  # where the search for a falling edge starts, in sender bit times
    while True:
        start = next((k for k in range(i, n) if line[k] == 0 and (k == 0 or line[k - 1])), None)
        if start is None:
            return bytes(out)
        if level(start + 0.5 * r):  # high again mid start bit: a glitch, not a character
            i = max(start + 1, int(start + 0.5 * r) + 1)
            continue
        value = sum(level(start + (1.5 + b) * r) << b for b in range(DATA_BITS))
        stop_at = start + (_FRAME_BITS - 0.5) * r
        out.append(value if level(stop_at) else 0)
        i = max(start + 1, int(stop_at) + 1)
