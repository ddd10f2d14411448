"""The LDQ-412 device model (docs/daq.md): a pure state machine.

No I/O, no threads, no clock of its own: the owner calls :meth:`LDQ412.sync` with the
current time (integer nanoseconds of the emulator's clock) before every access, and the
model produces every scan due up to that instant, in order. Lazy catch-up keeps the model
deterministic (the scans depend only on the schedule, never on when somebody looked) and
makes FIFO overflow exact. The owner serializes access (the model is not thread-safe).

Timing model
    Device time is microseconds since the current power-on, counted by the module's own
    clock: ``clock_ppm`` (:mod:`loopcal.simulator.open_points`) makes it run that much fast
    against the owner's clock. Scans happen at ``anchor_us + floor(j * 1e6 / rate)`` µs of
    device time for j = 0, 1, 2, ...: at power-on the anchor is ``scan_phase_us`` (0 by
    default: the first scan, counter 0, happens at once), and the module answers nothing
    before that first scan; a write that changes the scan rate re-anchors the schedule at
    the write's instant, the next scan following one new period later. Channel i
    (1-based) is converted ``(i - 1) * 250 us`` after the scan's time stamp; with
    oversampling N, the N conversions of a channel are modeled as a burst at that instant
    (the source is called N times with the same instants; only its noise differs).

Source time base
    The source sees seconds since the *first* power-on (``initial_uptime_s`` included) by
    the owner's clock, which equals device time until a power cycle (with a clock error,
    within it), and keeps running through power cycles (the LVDTs do not restart with the
    module).

Oversampling
    The reported code is the mean of N conversion codes rounded half up:
    ``(sum + N // 2) // N`` (what firmware does with ``(sum + N/2) >> log2 N``). Rounding
    to nearest keeps the mid-code reconstruction unbiased; truncation would bias every
    oversampled reading by about -0.5 LSB.

Power-on state (also after :meth:`LDQ412.power_cycle`)
    Counter 0, device time 0, empty FIFO, overflow clear, restart bit set, scan rate and
    ASCII checksum mode back to the power-on values given to the constructor, oversampling
    1. Injected channel faults (stuck, sensor fault, saturation) are physical and survive.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from loopcal.drivers.ldq412 import (
    CHANNEL_SKEW_S,
    CODE_MAX,
    FIFO_DEPTH,
    FIFO_FILLER,
    FIFO_MAX_SCANS_PER_READ,
    FIFO_SCAN_REGS,
    HR_ASCII_CHECKSUM,
    HR_CLEAR_FIFO,
    HR_CLEAR_RESTART,
    HR_COUNT,
    HR_OVERSAMPLING,
    HR_SCAN_RATE,
    IR_FIFO,
    IR_FIFO_END,
    IR_IDENTITY_LEN,
    IR_MODEL,
    IR_SNAPSHOT_LEN,
    MODEL_CODE,
    N_CHANNELS,
    OVERSAMPLING_CHOICES,
    POWER_CYCLE_S,
    SCAN_RATE_DEFAULT_HZ,
    SCAN_RATE_MAX_HZ,
    SCAN_RATE_MIN_HZ,
    STATUS_OVERFLOW,
    STATUS_RESTART,
    U32_MOD,
    V_MAX,
    V_MIN,
    split_u32,
    volts_to_code,
)

from .open_points import MODBUS_MAX_READ, OpenPoints
from .source import SignalSource

# Modbus exception codes the module answers (datasheet: 02 and 03; 01 for functions it
# does not implement).
ILLEGAL_FUNCTION = 0x01  #: Modbus exception 01, illegal function
ILLEGAL_ADDRESS = 0x02  #: Modbus exception 02, illegal data address
ILLEGAL_VALUE = 0x03  #: Modbus exception 03, illegal data value

# Protocol limit of a single Modbus register write (Modbus application spec; the read's,
# MODBUS_MAX_READ, is in open_points).
MODBUS_MAX_WRITE = 123
_NS_PER_S = 1_000_000_000
_IR_MAP_END = IR_MODEL + IR_IDENTITY_LEN  # one past the last input register

_US_PER_S = 1_000_000
_NS_PER_US = 1_000
_CHANNEL_OFFSETS_S = np.arange(N_CHANNELS) * CHANNEL_SKEW_S
# Analog levels beyond the converter's range, used to model a saturated conditioner.
_SATURATION_V = {"high": V_MAX + 1.0, "low": V_MIN - 1.0}


def rail_bits(codes: list[int]) -> int:
    """The status word's rail bits of a scan's codes.

    Parameters
    ----------
    codes : sequence of int
        Channel 1..4 codes, 0..4095.

    Returns
    -------
    int
        Bit ch (0-based) set for each channel at 0 or
        :data:`~loopcal.drivers.ldq412.CODE_MAX` (status bits 0-3); no other bit.
    """
    return sum(1 << ch for ch, c in enumerate(codes) if c in (0, CODE_MAX))


class DeviceError(Exception):
    """A request the module refuses with a Modbus exception code.

    The Modbus servers answer it as that exception; the ASCII protocol as ``?AA``.

    Parameters
    ----------
    code : int
        The exception code: 0x01 illegal function, 0x02 illegal data address, 0x03
        illegal data value (:data:`ILLEGAL_FUNCTION`, :data:`ILLEGAL_ADDRESS`,
        :data:`ILLEGAL_VALUE`).
    message : str
        Why, for people; the exception's text is ``exception CC: message``.

    Attributes
    ----------
    code : int
        As given.
    """

    def __init__(self, code: int, message: str) -> None:
        super().__init__(f"exception {code:02X}: {message}")
        self.code = code


class DeviceOffError(RuntimeError):
    """The module cannot be accessed: powered off, or before its first scan.

    Raised inside a power cycle, and after a power-on until its first scan is taken (see
    :attr:`LDQ412.ready`). The servers never let a request reach a module that is not
    ready (it answers nothing); this is the model's own guard.
    """


@dataclass(frozen=True, slots=True)
class TruthScan:
    """One scan exactly as the module produced it (ground truth for tests and calibration).

    Attributes
    ----------
    counter : int
        The scan counter as the module reports it, uint32 (wrapped).
    time_us : int
        Device time of the scan (channel 1's conversion) since the power-on, µs, uint32
        (wrapped).
    codes : tuple of 4 int
        Channel 1..4 codes, 0..4095.
    status : int
        The status register right after this scan was taken and pushed to the FIFO
        (bits 0-3 rail, 4-7 sensor fault, 8 FIFO overflow, 9 restart).
    t_s : float
        Source time of channel 1's instant, s since the first power-on.
    boot : int
        Power-on index, 0 for the first power-on, +1 per power cycle.
    """

    counter: int
    time_us: int
    codes: tuple[int, int, int, int]
    status: int
    t_s: float
    boot: int


def scans_due(uptime_us: int, rate_hz: int) -> int:
    """How many scans a schedule anchored at 0 has made by ``uptime_us``.

    Parameters
    ----------
    uptime_us : int
        Device time since the anchor, µs, >= 0.
    rate_hz : int
        Scan rate, Hz.

    Returns
    -------
    int
        The number of scans j >= 0 with ``floor(j * 1e6 / rate_hz) <= uptime_us``.
    """
    return ((uptime_us + 1) * rate_hz + _US_PER_S - 1) // _US_PER_S


class LDQ412:
    """The module's state: scanning, FIFO, registers, latches and channel faults.

    A pure state machine (module docstring): the owner calls :meth:`sync` with its clock's
    time before every access, and serializes access.

    Parameters
    ----------
    source : SignalSource
        The analog inputs (called N times per scan with oversampling N).
    now_ns : int, default 0
        The owner's clock at construction, ns; the module has been powered on for
        ``initial_uptime_s`` at that instant.
    scan_rate_hz : int, default 20
        Power-on value of holding register 0, the scan rate, 1..200 Hz.
    serial_number : int, default 0x00C0FFEE
        Serial number, uint32 (input registers 514-515).
    firmware : tuple of 2 int, default (2, 1)
        Firmware version (major 0..255, minor 0..99): input register 513 is
        ``major * 256 + minor``, ``$AAF`` answers ``M.mm``.
    ascii_checksum : bool, default False
        Power-on value of holding register 4, the ASCII checksum mode.
    initial_uptime_s : float, default 0.0
        How long the module has been on at ``now_ns``, s, >= 0 (for 32-bit wraps of the
        counter and device time). Only the last 256 scans of that time exist, in the FIFO,
        with the overflow flag latched if there were more.
    truth_limit : int or None, default None
        None: :attr:`truth` keeps every scan; N >= 1: it keeps the latest N to 2N-1.
    open_points : OpenPoints or None, default None
        The choices the datasheet leaves open (:class:`OpenPoints`; None is
        ``OpenPoints()``, the emulator as it always was).

    Attributes
    ----------
    source : SignalSource
        As given.
    serial_number : int
        As given.
    firmware : tuple of 2 int
        (major, minor), as given.
    power_on_scan_rate_hz : int
        The scan rate every power-on starts with, Hz.
    power_on_ascii_checksum : bool
        The checksum mode every power-on starts with.
    latest_reads : int
        How often a host read the latest scan (a snapshot or ``#AA``: each access of
        :attr:`latest`).
    fifo_reads : int
        How often a host read the FIFO window (each :meth:`pop_fifo`).
    truth : list of TruthScan
        Every scan the module produced, in order (bounded by ``truth_limit``); the owner
        may replace the list.
    truth_limit : int or None
        As given.
    open : OpenPoints
        The open points in force.

    Raises
    ------
    ValueError
        If ``truth_limit`` < 1, ``scan_rate_hz`` is outside 1..200, ``serial_number`` is
        not a uint32, ``firmware`` is out of range or ``initial_uptime_s`` is negative.
    """

    def __init__(
        self,
        source: SignalSource,
        *,
        now_ns: int = 0,
        scan_rate_hz: int = SCAN_RATE_DEFAULT_HZ,
        serial_number: int = 0x00C0FFEE,
        firmware: tuple[int, int] = (2, 1),
        ascii_checksum: bool = False,
        initial_uptime_s: float = 0.0,
        truth_limit: int | None = None,
        open_points: OpenPoints | None = None,
    ) -> None:
        if truth_limit is not None and truth_limit < 1:
            raise ValueError("truth_limit must be >= 1 or None")
        if not SCAN_RATE_MIN_HZ <= scan_rate_hz <= SCAN_RATE_MAX_HZ:
            raise ValueError(f"scan_rate_hz must be {SCAN_RATE_MIN_HZ}..{SCAN_RATE_MAX_HZ}")
        if not 0 <= serial_number < U32_MOD:
            raise ValueError("serial_number must be a uint32")
        major, minor = firmware
        if not (0 <= major <= 255 and 0 <= minor <= 99):
            raise ValueError("firmware must be (major 0..255, minor 0..99)")
        if initial_uptime_s < 0:
            raise ValueError("initial_uptime_s must be >= 0")
        self.source = source
        self.serial_number = serial_number
        self.firmware = (major, minor)
        self.power_on_scan_rate_hz = scan_rate_hz
        self.power_on_ascii_checksum = bool(ascii_checksum)
        # how often a host read the latest scan (a snapshot or ``#AA``), or the FIFO
        self.latest_reads = 0
        self.fifo_reads = 0
        self.truth: list[TruthScan] = []
        self.truth_limit = truth_limit
        self.open = open_points if open_points is not None else OpenPoints()
        # the module's clock error in parts per billion: integer arithmetic keeps it exact
        self._ppb = round(self.open.clock_ppm * 1000)

        self._stuck: list[int | None] = [None] * N_CHANNELS
        self._sensor_fault: list[bool] = [False] * N_CHANNELS
        self._saturate: list[str | None] = [None] * N_CHANNELS

        self._now_ns = now_ns
        self._first_boot_ns = now_ns - round(initial_uptime_s * 1e9)
        self._boot = -1
        self._off_until_ns: int | None = None
        self._power_on(self._first_boot_ns)
        # Powered on long ago and never read: only the last FIFO_DEPTH scans still exist.
        since_scan0 = self._device_us(now_ns) - self._anchor_us
        due = scans_due(since_scan0, scan_rate_hz) if since_scan0 >= 0 else 0
        skipped = max(0, due - FIFO_DEPTH)
        if skipped:
            self._next_j = skipped
            self._counter = skipped % U32_MOD
            self._overflow = True
        self.sync(now_ns)

    # ------------------------------------------------------------------ time

    def _device_us(self, now_ns: int) -> int:
        """Device time (µs since the current power-on, by the module's clock) at ``now_ns``."""
        elapsed = now_ns - self._boot_ns
        return (elapsed + elapsed * self._ppb // _NS_PER_S) // _NS_PER_US

    def _source_s(self, t_us: int) -> float:
        """Source time (s since the first power-on, by the owner's clock) of device time
        ``t_us`` of the current power-on."""
        if not self._ppb:
            return ((self._boot_ns - self._first_boot_ns) // _NS_PER_US + t_us) / _US_PER_S
        return (self._boot_ns - self._first_boot_ns + self._owner_ns(t_us)) / _NS_PER_S

    def _owner_ns(self, t_us: int) -> int:
        """Owner's-clock ns since the current power-on when the module's clock reads
        ``t_us`` (rounded down)."""
        return t_us * _NS_PER_US * _NS_PER_S // (_NS_PER_S + self._ppb)

    def _power_on(self, boot_ns: int) -> None:
        self._boot += 1
        self._boot_ns = boot_ns
        self._off_until_ns = None
        self._scan_rate = self.power_on_scan_rate_hz
        self._oversampling = 1
        self._ascii_checksum = self.power_on_ascii_checksum
        self._counter = 0
        self._anchor_us = self.open.scan_phase_us
        self._next_j = 0
        self._fifo: collections.deque[tuple[int, int, int, int, int]] = collections.deque()
        self._overflow = False
        self._restart = True
        self._latest: TruthScan | None = None
        self._latest_low_status = 0  # rail and fault bits of the latest scan

    def sync(self, now_ns: int) -> None:
        """Bring the module to time ``now_ns``: finish a power cycle, take due scans.

        Parameters
        ----------
        now_ns : int
            The owner's clock, ns. Time never goes back: an earlier ``now_ns`` than the
            last one is taken as the last one.

        Notes
        -----
        Every scan due up to ``now_ns`` is taken, in order, at its own scheduled instant
        (so the scans depend only on the schedule, not on when the module was synced).
        """
        now_ns = max(now_ns, self._now_ns)
        self._now_ns = now_ns
        if self._off_until_ns is not None:
            if now_ns < self._off_until_ns:
                return
            self._power_on(self._off_until_ns)
        uptime_us = self._device_us(now_ns)
        while True:
            t_us = self._next_scan_us()
            if t_us is None or t_us > uptime_us:
                break
            self._take_scan(t_us)
            self._next_j += 1

    def _next_scan_us(self) -> int | None:
        """Device time of the next scan of this power-on (None: it makes no more)."""
        return self._anchor_us + self._next_j * _US_PER_S // self._scan_rate

    @property
    def now_ns(self) -> int:
        """The owner's clock at the last :meth:`sync`, ns."""
        return self._now_ns

    @property
    def source_time_s(self) -> float:
        """Source time (s since the first power-on, by the owner's clock) as of the last
        :meth:`sync`: the time axis of scenarios and offset drifts."""
        return (self._now_ns - self._first_boot_ns) / _NS_PER_S

    @property
    def powered(self) -> bool:
        """False inside a power cycle, as of the last :meth:`sync` (True before the first
        scan of a power-on: see :attr:`ready`)."""
        return self._off_until_ns is None

    @property
    def boot(self) -> int:
        """Power-on index, 0 for the first power-on and +1 per completed power cycle."""
        return self._boot

    @property
    def ready(self) -> bool:
        """Whether the module answers requests (powered and past its first scan)."""
        return self._off_until_ns is None and self._latest is not None

    @property
    def uptime_us(self) -> int:
        """Device µs since the current power-on (unwrapped), as of the last sync."""
        return self._device_us(self._now_ns)

    def host_ns(self, boot: int, time64_us: int) -> int | None:
        """The owner's clock at a device time of the current power-on (when a scan was taken).

        Parameters
        ----------
        boot : int
            Power-on index (:attr:`boot`).
        time64_us : int
            Device time since that power-on, µs, unwrapped.

        Returns
        -------
        int or None
            The owner's clock at that device time, ns (the module's clock error taken
            out, rounded down); None if ``boot`` is not the current power-on.
        """
        if boot != self._boot:
            return None
        return self._boot_ns + self._owner_ns(time64_us)

    def power_cycle(self, off_s: float = POWER_CYCLE_S) -> None:
        """Switch the module off now and on again ``off_s`` seconds later.

        Scans due up to now are taken first; nothing is scanned while off. The power-on
        comes with the first :meth:`sync` at or after it (module docstring: power-on state).

        Parameters
        ----------
        off_s : float, default POWER_CYCLE_S
            How long it stays off, s of the owner's clock (the datasheet's 2 s by default).
        """
        self.sync(self._now_ns)
        self._off_until_ns = self._now_ns + round(off_s * 1e9)

    # ------------------------------------------------------------------ scans

    def _take_scan(self, t_us: int) -> None:
        n = self._oversampling
        t_s = self._source_s(t_us)
        instants = t_s + _CHANNEL_OFFSETS_S
        volts = np.empty((n, N_CHANNELS))
        for k in range(n):
            volts[k] = np.asarray(self.source.convert(instants.copy()), dtype=float)
        for ch, mode in enumerate(self._saturate):
            if mode is not None:
                volts[:, ch] = _SATURATION_V[mode]
        conv = volts_to_code(volts)
        mean = (conv.sum(axis=0) + n // 2) // n
        codes = [int(c) for c in mean]
        fault_bits = 0
        for ch in range(N_CHANNELS):
            if self._stuck[ch] is not None:
                codes[ch] = self._stuck[ch]
            if self._sensor_fault[ch]:
                codes[ch] = CODE_MAX
                fault_bits |= 1 << (4 + ch)
        self._push_scan(self._counter, t_us, codes, rail_bits(codes) | fault_bits, t_s)

    def _push_scan(
        self, counter: int, t_us: int, codes: list[int], low_status: int, t_s: float
    ) -> None:
        """Make a scan the latest and put it in the FIFO (low_status: rail and fault bits)."""
        if len(self._fifo) >= FIFO_DEPTH:
            self._fifo.popleft()
            self._overflow = True
        self._fifo.append((counter, *codes))
        self._latest_low_status = low_status
        self._latest = TruthScan(
            counter=counter,
            time_us=t_us % U32_MOD,
            codes=(codes[0], codes[1], codes[2], codes[3]),
            status=self.status,
            t_s=t_s,
            boot=self._boot,
        )
        self.truth.append(self._latest)
        if self.truth_limit is not None and len(self.truth) >= 2 * self.truth_limit:
            del self.truth[: -self.truth_limit]  # amortized O(1) per scan
        self._counter = (counter + 1) % U32_MOD

    def _require_power(self) -> None:
        if not self.ready:
            raise DeviceOffError("the module is powered off (or before its first scan)")

    @property
    def latest(self) -> TruthScan:
        """The latest scan (what registers 0..7 and ``#AA`` report).

        Each access counts as a host's read (:attr:`latest_reads`). Raises
        :class:`DeviceOffError` while the module is not :attr:`ready`.
        """
        self._require_power()
        assert self._latest is not None
        self.latest_reads += 1
        return self._latest

    @property
    def status(self) -> int:
        """The status register, the latest scan's rail and fault bits plus the latches.

        Bits 0-3 channel at the rail and 4-7 sensor fault, of the latest scan; bit 8 FIFO
        overflow (latched until 1 is written to holding register 2, or a power cycle) and
        bit 9 module restarted (set at power-on, latched until 1 is written to holding
        register 3).
        """
        return (
            self._latest_low_status
            | (STATUS_OVERFLOW if self._overflow else 0)
            | (STATUS_RESTART if self._restart else 0)
        )

    @property
    def fifo_level(self) -> int:
        """Scans waiting in the FIFO, 0..256 (input register 9)."""
        return len(self._fifo)

    @property
    def scan_rate_hz(self) -> int:
        """The scan rate in force, Hz (holding register 0)."""
        return self._scan_rate

    @property
    def oversampling(self) -> int:
        """Conversions averaged per code, 1, 2, 4, 8 or 16 (holding register 1)."""
        return self._oversampling

    @property
    def ascii_checksum(self) -> bool:
        """Holding register 4 (shared by Modbus and the ASCII protocol)."""
        return self._ascii_checksum

    @property
    def firmware_text(self) -> str:
        """Firmware version as ``M.mm`` (e.g. ``2.01``)."""
        return f"{self.firmware[0]}.{self.firmware[1]:02d}"

    # ------------------------------------------------------------------ registers

    def snapshot_registers(self) -> list[int]:
        """Input registers 0..9: one consistent view of the latest scan.

        Returns
        -------
        list of int
            Ten 16-bit registers: counter (hi, lo), device time in µs (hi, lo), channel
            1..4 codes, status, FIFO level.

        Raises
        ------
        DeviceOffError
            While the module is not :attr:`ready`.
        """
        s = self.latest
        return [
            *split_u32(s.counter),
            *split_u32(s.time_us),
            *s.codes,
            self.status,
            len(self._fifo),
        ]

    def identity_registers(self) -> list[int]:
        """Input registers 512..515: model, firmware, serial number.

        Returns
        -------
        list of int
            Four 16-bit registers: model code 0x0412, ``major * 256 + minor``, serial
            number (hi, lo).
        """
        major, minor = self.firmware
        return [MODEL_CODE, major * 256 + minor, *split_u32(self.serial_number)]

    def read_input_registers(self, address: int, count: int) -> list[int]:
        """Function 04, read input registers (a FIFO-window read pops its scans).

        Parameters
        ----------
        address : int
            First register, zero-based.
        count : int
            Registers asked for.

        Returns
        -------
        list of int
            The 16-bit registers: ``count`` of them, or fewer for a truncated read
            (``over_limit="truncate"``) or a short FIFO answer (``fifo_underrun="short"``).

        Raises
        ------
        DeviceError
            03 for a count outside 1..125 or a FIFO-window read whose count is not a
            multiple of 6; 02 for addresses outside 0..9, 256..375, 512..515, a
            FIFO-window read not starting at 256 or reading past 375 (more than 20
            scans). The open points change these answers (Notes).
        DeviceOffError
            While the module is not :attr:`ready`.

        Notes
        -----
        ``max_read_registers`` below 125 refuses a longer read with 03
        (``over_limit="refuse"``) or answers its first ``max_read_registers`` registers
        (``"truncate"``; in the FIFO window whole scans only, the rest left waiting);
        ``holes="zero"`` answers a read that leaves the listed blocks (unlisted registers
        0, the FIFO window 0xFFFF without taking a scan); ``snapshot_reads="whole"``
        refuses a read of part of 0..9 with 02 (:mod:`loopcal.simulator.open_points`).
        """
        self._require_power()
        if not 1 <= count <= MODBUS_MAX_READ:
            raise DeviceError(ILLEGAL_VALUE, f"count {count} outside 1..{MODBUS_MAX_READ}")
        op = self.open
        if count > op.max_read_registers:
            if op.over_limit == "refuse":
                raise DeviceError(
                    ILLEGAL_VALUE, f"count {count} over this module's {op.max_read_registers}"
                )
            count = op.max_read_registers
            if address == IR_FIFO:  # whole scans only; the rest stays waiting
                count -= count % FIFO_SCAN_REGS
                if not count:
                    raise DeviceError(ILLEGAL_VALUE, "not one whole FIFO scan fits a read")
        end = address + count
        if 0 <= address and end <= IR_SNAPSHOT_LEN:
            if op.snapshot_reads == "whole" and (address, count) != (0, IR_SNAPSHOT_LEN):
                raise DeviceError(ILLEGAL_ADDRESS, "the snapshot is read whole (0..9)")
            return self.snapshot_registers()[address:end]
        if IR_MODEL <= address and end <= _IR_MAP_END:
            return self.identity_registers()[address - IR_MODEL : end - IR_MODEL]
        if address == IR_FIFO and end <= IR_FIFO_END:
            if count % FIFO_SCAN_REGS:
                raise DeviceError(ILLEGAL_VALUE, f"FIFO read of {count} registers, not N*6")
            return self.pop_fifo(count // FIFO_SCAN_REGS)
        if op.holes == "zero" and 0 <= address and end <= _IR_MAP_END:
            return self._read_across_holes(address, end)
        raise DeviceError(ILLEGAL_ADDRESS, f"input registers {address}..{end - 1}")

    def _read_across_holes(self, address: int, end: int) -> list[int]:
        """A read that leaves the listed blocks, on a module that answers it: unlisted
        registers read 0, the snapshot and identity their values, and the FIFO window
        (not read from its start) 0xFFFF without taking any scan."""
        snap = self.snapshot_registers() if address < IR_SNAPSHOT_LEN else []
        ident = self.identity_registers() if end > IR_MODEL else []
        out = []
        for a in range(address, end):
            if a < IR_SNAPSHOT_LEN:
                out.append(snap[a])
            elif IR_FIFO <= a < IR_FIFO_END:
                out.append(FIFO_FILLER)
            elif a >= IR_MODEL:
                out.append(ident[a - IR_MODEL])
            else:
                out.append(0)
        return out

    def pop_fifo(self, n: int) -> list[int]:
        """Remove the ``n`` oldest scans; registers as the FIFO window returns them.

        Counts as a host's FIFO read (:attr:`fifo_reads`), whether any scan was waiting or
        not.

        Parameters
        ----------
        n : int
            Scans to take, 1..20.

        Returns
        -------
        list of int
            Six registers per scan (counter hi, counter lo, channel 1..4 codes), oldest
            first. Missing scans (fewer than ``n`` waiting) are all-0xFFFF filler scans,
            or left out (``fifo_underrun="short"``: the answer is shorter).

        Raises
        ------
        DeviceError
            03 for ``n`` outside 1..20.
        """
        if not 1 <= n <= FIFO_MAX_SCANS_PER_READ:
            raise DeviceError(ILLEGAL_VALUE, f"{n} scans per FIFO read")
        self.fifo_reads += 1
        regs: list[int] = []
        for _ in range(n):
            if self._fifo:
                counter, *codes = self._fifo.popleft()
                regs += [*split_u32(counter), *codes]
            elif self.open.fifo_underrun == "short":
                break
            else:
                regs += [FIFO_FILLER] * FIFO_SCAN_REGS
        return regs

    def holding_registers(self) -> list[int]:
        """Holding registers 0..4 as read.

        Returns
        -------
        list of int
            Scan rate (Hz), oversampling, 0, 0 (the command registers 2 and 3 read 0),
            ASCII checksum mode (0 or 1).
        """
        return [self._scan_rate, self._oversampling, 0, 0, int(self._ascii_checksum)]

    def read_holding_registers(self, address: int, count: int) -> list[int]:
        """Function 03, read holding registers.

        Parameters
        ----------
        address : int
            First register, zero-based.
        count : int
            Registers asked for.

        Returns
        -------
        list of int
            ``count`` registers of :meth:`holding_registers` from ``address``.

        Raises
        ------
        DeviceError
            03 for a count outside 1..125, 02 for registers outside 0..4.
        DeviceOffError
            While the module is not :attr:`ready`.
        """
        self._require_power()
        if not 1 <= count <= MODBUS_MAX_READ:
            raise DeviceError(ILLEGAL_VALUE, f"count {count} outside 1..{MODBUS_MAX_READ}")
        if not (0 <= address and address + count <= HR_COUNT):
            raise DeviceError(
                ILLEGAL_ADDRESS, f"holding registers {address}..{address + count - 1}"
            )
        return self.holding_registers()[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> None:
        """Functions 06 and 16, write holding registers (every value checked first).

        Values are applied in address order: 0 sets the scan rate (:meth:`set_scan_rate`),
        1 the oversampling, 1 written to 2 clears the FIFO and the overflow flag, 1
        written to 3 clears the restart flag, 4 sets the ASCII checksum mode.

        Parameters
        ----------
        address : int
            First register, zero-based.
        values : list of int
            The 16-bit values, one per register from ``address``.

        Raises
        ------
        DeviceError
            02 for registers outside 0..4; 03 for a count outside 1..123 or a value out
            of range: rate 1..200, oversampling 1/2/4/8/16, command registers 2 and 3
            take 0 (no-op) or 1, checksum mode 0 or 1. Nothing is applied then.
        DeviceOffError
            While the module is not :attr:`ready`.
        """
        self._require_power()
        if not 1 <= len(values) <= MODBUS_MAX_WRITE:
            raise DeviceError(ILLEGAL_VALUE, f"count {len(values)} outside 1..{MODBUS_MAX_WRITE}")
        if not (0 <= address and address + len(values) <= HR_COUNT):
            raise DeviceError(
                ILLEGAL_ADDRESS, f"holding registers {address}..{address + len(values) - 1}"
            )
        for reg, value in enumerate(values, start=address):
            if not _holding_value_ok(reg, value):
                raise DeviceError(ILLEGAL_VALUE, f"holding register {reg} = {value}")
        for reg, value in enumerate(values, start=address):
            if reg == HR_SCAN_RATE:
                self.set_scan_rate(value)
            elif reg == HR_OVERSAMPLING:
                self._oversampling = value
            elif reg == HR_CLEAR_FIFO and value == 1:
                self._fifo.clear()
                self._overflow = False
            elif reg == HR_CLEAR_RESTART and value == 1:
                self._restart = False
            elif reg == HR_ASCII_CHECKSUM:
                self._ascii_checksum = bool(value)

    def set_scan_rate(self, rate_hz: int) -> None:
        """Set the scan rate; a change re-anchors the schedule at the current time.

        Scans due up to now are taken at the old rate; the next scan follows one new
        period after now. The same rate again changes nothing.

        Parameters
        ----------
        rate_hz : int
            Scans per second, 1..200.

        Raises
        ------
        DeviceError
            03 for a rate outside 1..200.
        DeviceOffError
            While the module is not :attr:`ready`.
        """
        self._require_power()
        if not SCAN_RATE_MIN_HZ <= rate_hz <= SCAN_RATE_MAX_HZ:
            raise DeviceError(ILLEGAL_VALUE, f"scan rate {rate_hz} Hz")
        if rate_hz == self._scan_rate:
            return
        self.sync(self._now_ns)
        self._scan_rate = rate_hz
        self._anchor_us = self.uptime_us
        self._next_j = 1

    # ------------------------------------------------------------------ channel faults

    def set_stuck(self, channel: int, code: int | None) -> None:
        """Channel ``channel`` reports ``code`` on every scan from now on.

        Parameters
        ----------
        channel : int
            1..4.
        code : int or None
            The code, 0..4095; None releases the channel.

        Raises
        ------
        ValueError
            If ``channel`` is not 1..4 or ``code`` not 0..4095.
        """
        ch = _channel_index(channel)
        if code is not None and not 0 <= code <= CODE_MAX:
            raise ValueError(f"code must be 0..{CODE_MAX}")
        self._stuck[ch] = code

    def set_sensor_fault(self, channel: int, on: bool) -> None:
        """Sensor fault on a channel: it reads 4095 with its fault bit set.

        Parameters
        ----------
        channel : int
            1..4.
        on : bool
            True from the next scan on; False ends it.

        Raises
        ------
        ValueError
            If ``channel`` is not 1..4.
        """
        self._sensor_fault[_channel_index(channel)] = bool(on)

    def set_saturation(self, channel: int, mode: str | None) -> None:
        """The channel's conditioner output sits beyond the rail, or not.

        Parameters
        ----------
        channel : int
            1..4.
        mode : {"high", "low"} or None
            ``"high"``: 1 V above +10 V (code 4095); ``"low"``: 1 V below -10 V (code 0);
            None: the source's volts again.

        Raises
        ------
        ValueError
            If ``channel`` is not 1..4 or ``mode`` is none of those.
        """
        if mode not in (None, "high", "low"):
            raise ValueError('mode must be "high", "low" or None')
        self._saturate[_channel_index(channel)] = mode

    def clear_channel_faults(self) -> None:
        """Release every stuck channel, sensor fault and saturation."""
        self._stuck = [None] * N_CHANNELS
        self._sensor_fault = [False] * N_CHANNELS
        self._saturate = [None] * N_CHANNELS


def _channel_index(channel: int) -> int:
    if not 1 <= channel <= N_CHANNELS:
        raise ValueError(f"channel must be 1..{N_CHANNELS}, got {channel}")
    return channel - 1


def _holding_value_ok(reg: int, value: int) -> bool:
    if reg == HR_SCAN_RATE:
        return SCAN_RATE_MIN_HZ <= value <= SCAN_RATE_MAX_HZ
    if reg == HR_OVERSAMPLING:
        return value in OVERSAMPLING_CHOICES
    return value in (0, 1)
