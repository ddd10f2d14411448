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
    N_CHANNELS,
    POWER_CYCLE_S,
    SCAN_RATE_DEFAULT_HZ,
    SCAN_RATE_MAX_HZ,
    SCAN_RATE_MIN_HZ,
    STATUS_OVERFLOW,
    STATUS_RESTART,
    U32_MOD,
    V_MAX,
    V_MIN,
    volts_to_code,
)

from .open_points import OpenPoints
from .registers import ILLEGAL_VALUE, DeviceError, ModbusRegisters
from .source import SignalSource

_NS_PER_S = 1_000_000_000

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


class LDQ412(ModbusRegisters):
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
    # The model's side of FaultInjector's stuck_channel, sensor_fault and saturate (the
    # contract is documented there, once): each checks its arguments, a ValueError naming
    # the bad one, before it changes anything.

    def set_stuck(self, channel: int, code: int | None) -> None:
        """Channel ``channel`` (1..4) reports ``code`` (0..4095; None releases it) on every
        scan from now on (:meth:`~loopcal.simulator.faults.FaultInjector.stuck_channel`)."""
        ch = _channel_index(channel)
        if code is not None and not 0 <= code <= CODE_MAX:
            raise ValueError(f"code must be 0..{CODE_MAX}")
        self._stuck[ch] = code

    def set_sensor_fault(self, channel: int, on: bool) -> None:
        """Channel ``channel`` (1..4) reads 4095 with its fault bit set, or not
        (:meth:`~loopcal.simulator.faults.FaultInjector.sensor_fault`)."""
        self._sensor_fault[_channel_index(channel)] = bool(on)

    def set_saturation(self, channel: int, mode: str | None) -> None:
        """Channel ``channel``'s (1..4) conditioner output sits 1 V beyond the rail,
        ``mode`` ``"high"`` (+11 V, code 4095) or ``"low"`` (-11 V, code 0), or (None) is
        the source's volts again (:meth:`~loopcal.simulator.faults.FaultInjector.saturate`).
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
