"""Playing recorded scans back through the emulated module, scan for scan.

The caller hands over arrays (the simulator knows nothing of recording formats): for each
power-on of the module, the scans' counters, device times, codes and status as recorded.
:class:`RecordedModule` is a module that makes exactly those scans, whatever their phase,
gaps, wraps or restarts, so that a driver reading it gets the recorded counters, device
times, codes, missed counts, restarts and rail and fault bits (recording the replay gives
the recording back):

- each recorded scan happens at its own device time since its power-on (a recording that
  starts in the middle of a power-on starts with the module powered on that long ago);
  counters and device times are served modulo 2**32, as the module's registers hold them;
- scans the recording never received are not made again: the counter jumps over them, so
  a driver counts them as missed, as the recorder did;
- between power-ons the module is power-cycled (off as long as the recording shows, at
  most the datasheet's 2 s); a power-on whose first recorded scan came long after it (the
  recorder missed its beginning) starts that long ago, so nobody waits for it.

:class:`Player` drives the module's clock (a
:class:`~loopcal.simulator.clock.PlayClock`), ``speed`` times as fast as wall time, and
holds it still at the first and the last scan of each power-on until a client has read
them (the latest scan; and a client that reads the FIFO has emptied it and asked again,
so its answer reached it): a client that polls (ASCII) gets every power-on's first scan
however long it takes to reconnect, a power cycle never takes unread scans with it, and
a client that starts slowly misses nothing.

Not replayed: the overflow flag and the restart flag after it was cleared (they depend on
when a client read and cleared them, not on the scans), and FIFO scans' rail and fault bits
where a driver derives them (only measured status is the recorded one). Device times that
are not the counters' period apart replay exactly only where every time is measured (ASCII,
or Modbus with ``fifo=0``): FIFO scans' times are derived from the rate.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from loopcal.drivers.ldq412 import (
    CODE_MAX,
    POWER_CYCLE_S,
    SCAN_RATE_MAX_HZ,
    SCAN_RATE_MIN_HZ,
    STATUS_FAULT_MASK,
    STATUS_RAIL_MASK,
    U32_MOD,
)

from .choices import LINES
from .clock import PlayClock
from .device import LDQ412, rail_bits
from .emulator import Emulator
from .open_points import OpenPoints
from .source import ConstantSource

STEP_S = 0.01  # how often the player looks at the clock and the module
TAIL_S = 1.0  # device time served after the last scan, for the reader to catch up
HOLD_MAX_S = 30.0  # longest wall time a power-on's first scan waits for a reader
#: a power-on whose first recorded scan comes later than this after it starts earlier
FIRST_SCAN_LEAD_NS = 100_000_000
_NS_PER_US = 1_000
_LOW_STATUS = STATUS_RAIL_MASK | STATUS_FAULT_MASK


@dataclass(frozen=True)
class RecordedPowerOn:
    """The scans of one power-on as recorded.

    Attributes
    ----------
    counter : ndarray of int, shape (n,)
        Scan counters, unwrapped (may pass 2**32), n >= 1, >= 0, strictly increasing
        (gaps are scans the recording never received).
    time_us : ndarray of int, shape (n,)
        Device times since the power-on, µs, unwrapped, >= 0, strictly increasing.
    codes : ndarray of int, shape (n, 4)
        Channel 1..4 codes, 0..4095.
    status : ndarray of int, shape (n,), or None, default None
        Status words: their rail and fault bits (0-7) are served; None: rail bits from the
        codes, no faults.
    restart_latched : bool, default True
        The module's restart flag at the first scan (a recording that starts after a
        client cleared it: False). Only the first power-on's is used: every later one
        starts with the flag set, as a power-on does.
    off_s : float, default POWER_CYCLE_S
        How long the module was off before this power-on, s, in (0, 2] (the first
        power-on's is not used).

    Raises
    ------
    ValueError
        If the shapes do not match, n is 0, counters or times do not increase strictly
        or start below 0, a code is outside 0..4095, or ``off_s`` is outside (0, 2].
    """

    counter: np.ndarray
    time_us: np.ndarray
    codes: np.ndarray
    status: np.ndarray | None = None
    restart_latched: bool = True
    off_s: float = POWER_CYCLE_S

    def __post_init__(self) -> None:
        n = len(self.counter)
        if n == 0 or np.shape(self.time_us) != (n,) or np.shape(self.codes) != (n, 4):
            raise ValueError("a power-on needs n >= 1 counters, n times and (n, 4) codes")
        if self.status is not None and np.shape(self.status) != (n,):
            raise ValueError("a power-on's status needs one word per scan")
        if np.any(np.diff(self.counter) <= 0) or np.any(np.diff(self.time_us) <= 0):
            raise ValueError("counters and times of a power-on must increase")
        if self.counter[0] < 0 or self.time_us[0] < 0:
            raise ValueError("counters and times start at 0 at power-on")
        if np.any(self.codes < 0) or np.any(self.codes > CODE_MAX):
            raise ValueError(f"codes must be 0..{CODE_MAX}")
        if not 0 < self.off_s <= POWER_CYCLE_S:
            raise ValueError(f"off_s must be in (0, {POWER_CYCLE_S}] s")


class RecordedModule(LDQ412):
    """An LDQ-412 whose power-on k makes exactly the scans of ``power_ons[k]``.

    After its last scan a power-on makes none until the next power cycle; after the last
    power-on, none at all. Registers, FIFO, flags and faults are the model's
    (:class:`~loopcal.simulator.device.LDQ412`).

    Parameters
    ----------
    power_ons : list of RecordedPowerOn
        The power-ons to serve, in order (at least one).
    rate_hz : int
        The recording's scan rate, 1..200 Hz (holding register 0, and the period a driver
        derives FIFO scans' times from).
    now_ns : int, default 0
        The owner's clock, ns; the first recorded scan is taken then (the module has been
        on for that scan's device time).
    open_points : OpenPoints or None, default None
        How the module answers (FIFO underrun, read limits, holes, snapshot reads); its
        scans' phase and clock are the recording's, so ``scan_phase_us`` and
        ``clock_ppm`` must be left at their defaults.

    Attributes
    ----------
    power_ons : list of RecordedPowerOn
        As given.

    Raises
    ------
    ValueError
        If ``power_ons`` is empty, ``rate_hz`` is outside 1..200, or ``open_points`` sets
        a scan phase or a clock error.
    """

    def __init__(
        self,
        power_ons: list[RecordedPowerOn],
        *,
        rate_hz: int,
        now_ns: int = 0,
        open_points: OpenPoints | None = None,
    ) -> None:
        if not power_ons:
            raise ValueError("nothing to replay")
        if not SCAN_RATE_MIN_HZ <= rate_hz <= SCAN_RATE_MAX_HZ:
            raise ValueError(f"scan rate {rate_hz} Hz outside the datasheet's range")
        op = open_points or OpenPoints()
        if op.scan_phase_us or op.clock_ppm:
            raise ValueError("a replay's scan phase and clock are the recording's")
        self.power_ons = power_ons
        self._i = 0  # next scan of the current power-on
        super().__init__(
            ConstantSource([0.0] * 4), now_ns=now_ns, scan_rate_hz=rate_hz, open_points=op
        )
        self._overflow = False  # the base counts scans "before" the first as dropped

    def _power_on(self, boot_ns: int) -> None:
        super()._power_on(boot_ns)
        self._i = 0
        if self._boot < len(self.power_ons):
            first_ns = int(self.power_ons[self._boot].time_us[0]) * _NS_PER_US
            lead = FIRST_SCAN_LEAD_NS if self._boot else 0
            self._boot_ns -= max(0, first_ns - lead)  # it has been on that long
            if self._boot == 0:
                self._first_boot_ns = self._boot_ns
                self._restart = self.power_ons[0].restart_latched

    @property
    def power_on(self) -> RecordedPowerOn | None:
        """The recorded power-on being served (:class:`RecordedPowerOn`; None after the last)."""
        return self.power_ons[self._boot] if self._boot < len(self.power_ons) else None

    def _next_scan_us(self) -> int | None:
        po = self.power_on
        if po is None or self._i >= len(po.counter):
            return None
        return int(po.time_us[self._i])

    def _take_scan(self, t_us: int) -> None:
        po = self.power_on
        assert po is not None
        i = self._i
        self._i += 1
        codes = [int(c) for c in po.codes[i]]
        if po.status is not None:
            low = int(po.status[i]) & _LOW_STATUS
        else:
            low = rail_bits(codes)
        self._push_scan(int(po.counter[i]) % U32_MOD, t_us, codes, low, self._source_s(t_us))


class Player:
    """Serve recorded power-ons on an emulated module (``loopcal replay``).

    The emulator starts with :meth:`start` (or ``with``); its :attr:`url` is what a driver
    opens; :meth:`run` plays until the end or ``stop``.

    Parameters
    ----------
    power_ons : list of RecordedPowerOn
        The recording's power-ons, in order (at least one).
    transport : {"modbus-tcp", "modbus-rtu", "ascii"}, default "modbus-tcp"
        The wire.
    rate_hz : int, default 20
        The recording's scan rate, Hz.
    speed : float, default 1.0
        Device seconds per wall second, > 0 (an ASCII client polls at the module's own
        rate, so ASCII replays at 1).
    host : str, default "127.0.0.1"
        TCP listening address.
    port : int, default 0
        TCP port; 0: a free one.
    seed : int, default 0
        Seeds the answer delays and garbage bytes.
    open_points : OpenPoints or None, default None
        How the module answers (latency, FIFO underrun, read limits); no scan phase or
        clock error.
    line : {"pty", "tcp"}, default "pty"
        A serial transport's line (:class:`~loopcal.simulator.emulator.Emulator`).

    Attributes
    ----------
    power_ons : list of RecordedPowerOn
        As given.
    speed : float
        As given.
    period_ns : int
        The scan period, ns (``1e9 // rate_hz``).
    clock : PlayClock
        The module's clock, run by :meth:`run`.
    module : RecordedModule
        The device model served.
    emulator : Emulator
        The emulator serving it.

    Raises
    ------
    ValueError
        If ``power_ons`` is empty, ``speed`` is not > 0, or the module or the emulator
        refuse their settings (:class:`RecordedModule`,
        :class:`~loopcal.simulator.emulator.Emulator`).
    """

    def __init__(
        self,
        power_ons: list[RecordedPowerOn],
        *,
        transport: str = "modbus-tcp",
        rate_hz: int = 20,
        speed: float = 1.0,
        host: str = "127.0.0.1",
        port: int = 0,
        seed: int = 0,
        open_points: OpenPoints | None = None,
        line: str = LINES[0],
    ) -> None:
        if not power_ons:
            raise ValueError("nothing to replay")
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.power_ons = power_ons
        self.speed = float(speed)
        self.period_ns = 1_000_000_000 // rate_hz
        self.clock = PlayClock(speed)
        self.module = RecordedModule(
            power_ons, rate_hz=rate_hz, now_ns=self.clock.now_ns(), open_points=open_points
        )
        self.emulator = Emulator(
            transport, clock=self.clock, seed=seed, host=host, port=port, device=self.module,
            open_points=open_points, line=line,
        )  # fmt: skip

    @property
    def url(self) -> str:
        """What a driver opens (the emulator's URL); empty until started.

        See :attr:`~loopcal.simulator.emulator.Emulator.url`.
        """
        return self.emulator.url

    def start(self) -> Player:
        """Start the emulator's servers; returns once :attr:`url` is reachable.

        Returns
        -------
        Player
            ``self``.

        Raises
        ------
        RuntimeError
            If the servers could not start
            (:meth:`~loopcal.simulator.emulator.Emulator.start`).
        TimeoutError
            If they were not up within 5 s.
        """
        self.emulator.start()
        return self

    def close(self) -> None:
        """Stop the emulator's servers (:meth:`~loopcal.simulator.emulator.Emulator.close`)."""
        self.emulator.close()

    def __enter__(self) -> Player:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run(self, stop: threading.Event | None = None, *, wait_for_client: bool = False) -> bool:
        """Play every power-on to its end, or until ``stop``.

        Blocks. Between power-ons the module is switched off half a period after the
        last scan, for the next power-on's ``off_s``. The clock is held at each later
        power-on's first scan until a client has read the latest scan, and at the last
        scan of each power-on until it has (and, a client that reads the FIFO, emptied
        it and asked again: :meth:`_hold`), at most 30 s of wall time each (the last of
        all only if a client has read the module: a replay nobody reads ends on time);
        then it plays 1 s more. A reader that keeps up gets every scan before the module
        goes away.

        Parameters
        ----------
        stop : threading.Event or None, default None
            Set it to end the replay early (from another thread, or a signal handler).
        wait_for_client : bool, default False
            Hold the first scan until a client has read it (later power-ons' first scans
            are always held so), so that a client that starts slowly misses nothing of
            the recording.

        Returns
        -------
        bool
            True if it played to the end, False if stopped.
        """
        stop = stop or threading.Event()
        for k, po in enumerate(self.power_ons):
            if k:
                # switched off half a period after its last scan, on again off_s later
                self._play_until(self.clock.now_ns() + self.period_ns // 2, stop)
                self.emulator.faults.restart(po.off_s)
                self._play_until(self.clock.now_ns() + round(po.off_s * 1e9), stop)
                with self.emulator.lock:
                    self.module.sync(self.clock.now_ns())
                    first = self.module.host_ns(k, int(po.time_us[0]))
                assert first is not None
                self._play_until(first, stop)
            if (k or wait_for_client) and not self._hold(stop):
                return False
            with self.emulator.lock:
                last = self.module.host_ns(k, int(po.time_us[-1]))
            assert last is not None
            if not self._play_until(last, stop):
                return False
            if (k + 1 < len(self.power_ons) or self._has_client()) and not self._hold(
                stop, drained=True
            ):
                return False
        return self._play_until(self.clock.now_ns() + round(TAIL_S * 1e9), stop)

    def _has_client(self) -> bool:
        """Whether a client has read the module at all (the last scan is held for one)."""
        with self.emulator.lock:
            return self.module.latest_reads > 0 or self.module.fifo_reads > 0

    def _play_until(self, target_ns: int, stop: threading.Event) -> bool:
        """Let the clock run to ``target_ns`` at ``speed`` times wall time, and wait until it
        is there (False: stopped)."""
        self.clock.run_until(target_ns)
        while not stop.is_set():
            if self.clock.now_ns() >= target_ns:
                return True
            stop.wait(STEP_S)
        return False

    def _hold(self, stop: threading.Event, *, drained: bool = False) -> bool:
        """Keep the clock still until a client reads the latest scan (at most
        :data:`HOLD_MAX_S`); False if stopped.

        ``drained``: a client that reads the FIFO must also have emptied it, and read the
        module again after that. A FIFO read pops its scans before its answer leaves (and
        a Modbus answer can be held back by the module's latency): only the client's next
        request shows that the answer reached it, so that a power cycle closing the
        connection now takes no answer with it.
        """
        with self.emulator.lock:
            self.module.sync(self.clock.now_ns())
            reads = self.module.latest_reads
        emptied_at: int | None = None  # latest reads when the FIFO was seen empty
        deadline = time.monotonic() + HOLD_MAX_S
        while not stop.is_set():
            with self.emulator.lock:
                m = self.module
                if not drained or not m.fifo_reads:
                    done = m.latest_reads > reads
                else:
                    if emptied_at is None and not m.fifo_level:
                        emptied_at = m.latest_reads
                    done = emptied_at is not None and m.latest_reads > emptied_at
                if done:
                    return True
            if time.monotonic() > deadline:
                return True
            stop.wait(STEP_S / 2)
        return False
