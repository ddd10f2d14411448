"""The records a driver returns: :class:`Scan` (one scan of the four channels) and
:class:`Identity` (what the module says it is).

They live apart from :mod:`loopcal.drivers.base` so that the sequencer, which builds the
scans, and the DAQ base class, which holds a sequencer, can both import them without an
import cycle; ``loopcal.drivers`` and ``loopcal.drivers.base`` export them as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from . import ldq412

if TYPE_CHECKING:  # imported by Scan.volts: the records' module is loaded by a --help
    import numpy as np

ScanSource = Literal["fifo", "snapshot"]


@dataclass(frozen=True, slots=True)
class Identity:
    """What the module says it is, read at connect (:attr:`DAQ.identity`).

    Attributes
    ----------
    model : str
        Model name, ``"LDQ412"``; Modbus: derived from the model code 0x0412 in input
        register 512 (another code gives ``"unknown-0x...."``); ASCII: the ``$AAM``
        answer verbatim.
    firmware : str
        Firmware version as ``"M.mm"``, e.g. ``"2.01"``.
    serial : int or None
        Serial number (input registers 514-515), or None over ASCII, whose command set
        has no serial-number query.
    model_code : int or None
        The raw model code (Modbus), or None over ASCII.
    """

    model: str
    firmware: str
    serial: int | None
    model_code: int | None = None

    @property
    def firmware_version(self) -> tuple[int, int]:
        """The firmware as ``(major, minor)``, e.g. ``(2, 1)`` for ``"2.01"``.

        Raises
        ------
        ValueError
            If :attr:`firmware` is not ``"M.mm"`` (the drivers never build one that is not).
        """
        major, minor = self.firmware.split(".")
        return int(major), int(minor)


@dataclass(frozen=True, slots=True)
class Scan:
    """One scan of the four channels, as delivered by a driver.

    The raw fields are what the device reports (32-bit, wrapping); the unwrapped fields,
    the events and the provenance are the driver's (:mod:`loopcal.drivers.sequence`).
    Events are true on the first scan delivered after the event, and never hidden.

    Attributes
    ----------
    counter : int
        Raw scan counter, 0..2**32-1 (0 at power-on, +1 per scan).
    time_us : int
        Raw device time of channel 1's conversion, µs, 0..2**32-1.
    codes : tuple of 4 int
        Channel 1..4 ADC codes, 0..4095.
    status : int
        Status register: bits 0-3 rail, 4-7 sensor fault, 8 FIFO overflow latched, 9
        restart latched.
    counter64 : int
        Scans since the device's power-on, never wraps.
    time64_us : int
        µs of device time since power-on, never wraps. The 32-bit wraps before the first
        scan the driver saw (of each power-on epoch) are estimated from counter64 x the
        nominal scan period.
    epoch : int
        Device restarts this driver detected before this scan; ``(epoch, counter64)``
        increases strictly from scan to scan.
    missed : int
        Scans the device made just before this one that the driver never delivered (a
        counter gap: FIFO overflow, a lost FIFO answer, or polling slower than the scan
        rate). After a restart: the new power-on epoch's scans before this one (the old
        epoch's undelivered tail is unknowable).
    restarted : bool
        The device restarted (power cycle) before this scan, seen by the restart status
        bit or the counter going backwards. Also true on the first scan after connect if
        the restart bit was set then.
    overflow : bool
        The device's FIFO overflowed before this scan: bit 8 rising, or a counter gap in
        the FIFO after the module made at least its depth (256 scans) since the scan
        delivered before it (the driver never clears the bit, since that would empty the
        FIFO too, so a latched bit says nothing about later gaps). Only FIFO reads report
        it.
    taken : bool
        The scans missed just before this one were taken off the module's FIFO by another
        reader (another Modbus master reading the FIFO window): a counter gap that neither
        an overflow nor a FIFO answer lost on the way explains
        (:mod:`loopcal.drivers.sequence`). ``missed`` counts them as for any gap. Only
        FIFO reads report it.
    time_measured : bool
        ``time_us`` came from the device (snapshot, ``#AA``). False for FIFO scans, whose
        time is derived: anchor time + (counter - anchor counter) x 1e6 / scan rate,
        anchored on the snapshot read in the same call.
    status_measured : bool
        ``status`` came from the device for this very scan. False for FIFO scans: rail
        bits computed from the codes, fault bits the snapshot's on channels reading 4095,
        bits 8-9 the snapshot's.
    source : {"fifo", "snapshot"}
        Where the scan was read.
    host_time : float
        ``time.monotonic()`` when the answer carrying this scan arrived, s (for the FIFO
        scan that is also its batch's anchor snapshot: when the snapshot arrived, the
        earliest answer that carried it).
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
    taken: bool = False
    time_measured: bool = True
    status_measured: bool = True
    source: ScanSource = "snapshot"
    host_time: float = 0.0

    @property
    def rail(self) -> tuple[bool, bool, bool, bool]:
        """Per channel 1..4: at the rail (code 0 or 4095), by status bits 0-3."""
        return _bits(self.status, 0)

    @property
    def fault(self) -> tuple[bool, bool, bool, bool]:
        """Per channel 1..4: sensor fault (excitation lost, cable cut), by status bits 4-7."""
        return _bits(self.status, 4)

    @property
    def overflow_latched(self) -> bool:
        """Status bit 8 as read: a FIFO overflow latched in the device."""
        return bool(self.status & ldq412.STATUS_OVERFLOW)

    @property
    def restart_latched(self) -> bool:
        """Status bit 9 as read: a restart latched in the device."""
        return bool(self.status & ldq412.STATUS_RESTART)

    @property
    def trustworthy(self) -> tuple[bool, bool, bool, bool]:
        """Per channel 1..4: neither at the rail nor faulted."""
        r, f = self.rail, self.fault
        return (
            not (r[0] or f[0]),
            not (r[1] or f[1]),
            not (r[2] or f[2]),
            not (r[3] or f[3]),
        )

    @property
    def volts(self) -> np.ndarray:
        """Channel 1..4 voltages by mid-code reconstruction, V, shape (4,), float64."""
        import numpy as np

        return ldq412.code_to_volts(np.asarray(self.codes))

    @property
    def time_s(self) -> float:
        """Unwrapped device time, s (``time64_us`` x 1e-6)."""
        return self.time64_us * 1e-6


def _bits(status: int, shift: int) -> tuple[bool, bool, bool, bool]:
    return (
        bool(status >> shift & 1),
        bool(status >> (shift + 1) & 1),
        bool(status >> (shift + 2) & 1),
        bool(status >> (shift + 3) & 1),
    )
