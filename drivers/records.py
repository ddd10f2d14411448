"""The records a driver returns: :class:`Scan` (one scan of the four channels) and
:class:`Identity` (what the module says it is).

They live apart from :mod:`loopcal.drivers.base` so that the sequencer, which builds the
scans, and the DAQ base class, which holds a sequencer, can both import them without an
import cycle; ``loopcal.drivers`` and ``loopcal.drivers.base`` export them as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from . import ldq412

ScanSource = Literal["fifo", "snapshot"]


@dataclass(frozen=True, slots=True)
class Identity:
    """What the module says it is, read at connect.

    model: model name, ``"LDQ412"`` (Modbus: derived from model code 0x0412 in register
        512; ASCII: the ``$AAM`` answer verbatim).
    firmware: version as ``"M.mm"``, e.g. ``"2.01"``.
    serial: serial number (registers 514-515), or None over ASCII, whose command set has
        no serial-number query.
    model_code: raw model code (Modbus), or None over ASCII.
    """

    model: str
    firmware: str
    serial: int | None
    model_code: int | None = None

    @property
    def firmware_version(self) -> tuple[int, int]:
        """Firmware as (major, minor)."""
        major, minor = self.firmware.split(".")
        return int(major), int(minor)


@dataclass(frozen=True, slots=True)
class Scan:
    """One scan of the four channels, as delivered by a driver.

    Raw fields (what the device reports, 32-bit, wrapping):
        counter: scan counter, 0..2**32-1 (0 at power-on, +1 per scan).
        time_us: device time of channel 1's conversion, µs, 0..2**32-1.
        codes: channel 1..4 ADC codes, 0..4095.
        status: status register (bits 0-3 rail, 4-7 sensor fault, 8 FIFO overflow
            latched, 9 restart latched).

    Unwrapped fields (computed by the driver):
        counter64: scans since the device's power-on, never wraps.
        time64_us: µs of device time since power-on, never wraps. The number of 32-bit
            wraps before the first scan the driver saw (of each power-on epoch) is
            estimated from counter64 x the nominal scan period.
        epoch: number of device restarts this driver detected before this scan;
            (epoch, counter64) increases strictly from scan to scan.

    Events (true on the first scan delivered after the event; never hidden):
        missed: scans the device produced immediately before this one that the driver
            never delivered (counter gap; FIFO overflow or polling slower than the scan
            rate). After a restart: the new power-on epoch's scans before this one
            (the old epoch's undelivered tail is unknowable).
        restarted: the device restarted (power cycle) before this scan, detected by the
            restart status bit or the counter going backwards. Also true on the first
            scan after connect if the restart bit was set then.
        overflow: the device's FIFO overflowed before this scan (bit 8 rising, or a
            counter gap in the FIFO while bit 8 is latched; the driver never clears the
            bit, since that would empty the FIFO too). Only FIFO reads report it.

    Provenance:
        time_measured: time_us came from the device (snapshot / ``#AA``); False for FIFO
            scans, whose time is derived: anchor time + (counter - anchor counter) x
            1e6 / scan rate, anchored on the snapshot read in the same call.
        status_measured: status came from the device for this very scan. False for FIFO
            scans: rail bits are then computed from the codes, fault bits are the
            snapshot's fault bits on channels reading 4095, bits 8-9 the snapshot's.
        source: "fifo" or "snapshot".
        host_time: time.monotonic() when the answer carrying this scan arrived, s (for the
            FIFO scan that is also the batch's anchor snapshot: when the snapshot arrived,
            the earliest answer that carried it).
    """

    counter: int
    time_us: int
    codes: tuple[int, int, int, int]
    status: int
    counter64: int
    time64_us: int
    epoch: int = 0
    missed: int = 0
    restarted: bool = False
    overflow: bool = False
    time_measured: bool = True
    status_measured: bool = True
    source: ScanSource = "snapshot"
    host_time: float = 0.0

    @property
    def rail(self) -> tuple[bool, bool, bool, bool]:
        """Per channel: at the rail (code 0 or 4095) per status bits 0-3."""
        return _bits(self.status, 0)

    @property
    def fault(self) -> tuple[bool, bool, bool, bool]:
        """Per channel: sensor fault (excitation lost, cable cut) per status bits 4-7."""
        return _bits(self.status, 4)

    @property
    def overflow_latched(self) -> bool:
        """Status bit 8 as read (FIFO overflow latched in the device)."""
        return bool(self.status & ldq412.STATUS_OVERFLOW)

    @property
    def restart_latched(self) -> bool:
        """Status bit 9 as read (restart latched in the device)."""
        return bool(self.status & ldq412.STATUS_RESTART)

    @property
    def trustworthy(self) -> tuple[bool, bool, bool, bool]:
        """Per channel: neither at the rail nor faulted."""
        r, f = self.rail, self.fault
        return (
            not (r[0] or f[0]),
            not (r[1] or f[1]),
            not (r[2] or f[2]),
            not (r[3] or f[3]),
        )

    @property
    def volts(self) -> np.ndarray:
        """Channel voltages by mid-code reconstruction, V, shape (4,)."""
        return ldq412.code_to_volts(np.asarray(self.codes))

    @property
    def time_s(self) -> float:
        """Unwrapped device time, s."""
        return self.time64_us * 1e-6


def _bits(status: int, shift: int) -> tuple[bool, bool, bool, bool]:
    return (
        bool(status >> shift & 1),
        bool(status >> (shift + 1) & 1),
        bool(status >> (shift + 2) & 1),
        bool(status >> (shift + 3) & 1),
    )
