"""DAQ -> scans: the loop that reads the LDQ-412 and hands every scan on, with its events.

:class:`Acquisition` runs in a thread of its own and never waits for the disk: it reads the
module, turns the driver's :class:`loopcal.drivers.Scan` records into rows of
:data:`loopcal.daemon.scan_rows.SCAN_DTYPE` and gives each batch to a sink (the recorder's queue).

What it adds to the driver's scans:

- a power-on **epoch** that survives the recorder: started with the last scan already
  recorded (a :class:`ResumePoint`), it stays the same while the module keeps its power-on
  and the counter moves on, and goes up by one when the module restarted (restart bit,
  counter going backwards) or another module answers at the URL. The scans lost while
  nobody read the module are counted on the first scan read (``missed``) and reported;
- UTC time stamps: ``host_ns`` when the answer arrived, and ``stamp_ns``, the acquisition
  instant, from the module's own clock mapped to UTC by the lower envelope of
  (arrival - device time), which follows the module's clock error
  (:mod:`loopcal.daemon.recorder.clockmap`). Stamps strictly increase over everything it
  hands on, across restarts and reconnects (each power-on's map starts from the last
  one's floor), and step back only when the host's clock was set back;
- events: gaps, restarts, FIFO overflow, rail and sensor faults (onset at once, end after a
  second of clear scans, so a channel flickering at the rail does not flood the log),
  the link going down and coming back, and another Modbus master taking scans off the
  FIFO (one ``foreign_reader`` warning when it starts, one event when it stops:
  :mod:`loopcal.daemon.recorder.foreign`; its gaps are info, each scan still missed).

When the module stops answering, the loop says why
(:func:`loopcal.drivers.diagnosis.diagnose` on the driver's error, as ``loopcal probe``
would say it, without a byte more on the wire): in the ``disconnect`` event, then in one
WARNING line every ``report_every`` s (30 by default) while it lasts, and in
:attr:`Acquisition.diagnosis` for the status line. It retries every 0.05 s through the
datasheet's restart window (a power-cycled module answers again within 2 s), then with
exponential backoff (0.1 s doubling to 2 s, or to a quarter of what the FIFO holds: far
inside it), so a short outage loses nothing over Modbus and little over ASCII. The FIFO is
read every
``read_period`` plus a dither (and again at once if it was more than half full); without a
FIFO (ASCII, or Modbus with ``fifo=0``) the loop polls once per scan, phase-locked to the
module's own clock: the pacers of the driver's own scan stream
(:mod:`loopcal.drivers.pacing`). The loop does not read through that stream
(:meth:`loopcal.drivers.DAQ.scans`): it stamps and hands on each read's scans as one batch,
adds the events of a read (a gap, a link down) as they happen rather than after a
timeout, and reconnects on its own schedule (the restart window, then backoff), none of
which a stream of single scans tells.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from loopcal.drivers import DAQ, DAQError, Scan, ldq412, open_daq
from loopcal.drivers.diagnosis import Diagnosis, diagnose
from loopcal.drivers.pacing import FIFO_READ_PERIOD_S, FifoPacer, PollPacer

from ..events import Event, Level
from ..scan_rows import SCAN_DTYPE
from .batches import AcquisitionStats, Batch, DeviceInfo, ResumePoint
from .clockmap import ClockMap, StampFloor
from .foreign import ForeignReaders
from .settings import UNREACHABLE_REPORT_S

log = logging.getLogger(__name__)

BACKOFF_FAST_S = 0.05  # retry period while a power-cycled module may be coming back
RESTART_WINDOW_S = ldq412.POWER_CYCLE_S + 0.5  # the datasheet's 2 s, and some
BACKOFF_MIN_S = 0.1
BACKOFF_MAX_S = 2.0
FAULT_CLEAR_S = 1.0  # a rail or fault condition ends after this long of clear scans
#: the reason of a gap another Modbus master took (Scan.taken)
TAKEN_REASON = "taken by another reader of the module's FIFO"


class _Flag:
    """A rail or fault condition of one channel: on at once, off after a clear stretch."""

    def __init__(self) -> None:
        self.on = False
        self.clear_since: int | None = None  # stamp_ns of the first clear scan
        self.clear_counter = 0  # its counter64: where the condition ended
        self.clear_epoch = 0


class Acquisition:
    """Reads the module at ``url`` until stopped, giving every batch of scans to ``sink``.

    url: driver URL (see :func:`loopcal.drivers.open_daq`). timeout: s without an answer before a
    call fails. read_period: s between FIFO reads. resume: the last scan already recorded.
    sink: called from the acquisition thread with each :class:`Batch`; must not block.
    report_every: s between two WARNING lines saying why the module cannot be reached,
    while it cannot (:attr:`report_every`, which a reload may change).
    """

    def __init__(
        self,
        url: str,
        sink: Callable[[Batch], None],
        *,
        timeout: float = ldq412.HOST_TIMEOUT_S,
        read_period: float = FIFO_READ_PERIOD_S,
        resume: ResumePoint | None = None,
        report_every: float = UNREACHABLE_REPORT_S,
    ) -> None:
        if not timeout > 0:
            raise ValueError(f"timeout must be > 0 s, got {timeout}")
        if not 0 < read_period <= 5.0:
            raise ValueError(f"read period must be in (0, 5] s, got {read_period}")
        self.url = url
        self.sink = sink
        self.timeout = timeout
        self.report_every = report_every
        #: why the module cannot be reached, while it cannot (None while it answers)
        self.diagnosis: Diagnosis | None = None
        self.stats = AcquisitionStats()
        self.device: DeviceInfo | None = None
        #: monotonic time of the loop's last turn (a watchdog reads it)
        self.heartbeat = time.monotonic()
        self._daq: DAQ | None = None
        self._last: ResumePoint | None = resume
        self._base_epoch: int | None = None  # recorded epoch = base + driver epoch
        self._clocks: dict[int, ClockMap] = {}
        #: the last stamp handed on: every map starts after it (a restart, a reconnect)
        self._floor: StampFloor | None = resume.floor if resume is not None else None
        self._rail = [_Flag() for _ in range(4)]
        self._fault = [_Flag() for _ in range(4)]
        self._down_since: float | None = None
        self._down_logged = 0.0
        self._backoff = BACKOFF_MIN_S
        self._pending_events: list[Event] = []
        self._first_missed: int | None = None
        self._clock_hint: tuple[int, float, int, int] | None = None
        self.fifo_pacer = FifoPacer(read_period)  # with a FIFO: when to read
        self.poll_pacer: PollPacer | None = None  # without a FIFO: when to poll
        self._seen_driver_epochs: set[int] = set()
        self._foreign = ForeignReaders()

    @property
    def resume_point(self) -> ResumePoint | None:
        """The last scan handed on (where another acquisition would carry on)."""
        return self._last

    @property
    def _rate_hz(self) -> int:
        """The module's scan rate (the datasheet's default before it is identified)."""
        return self.device.scan_rate_hz if self.device else ldq412.SCAN_RATE_DEFAULT_HZ

    # ------------------------------------------------------------------ thread body

    def run(self, stop: threading.Event) -> None:
        """Read until ``stop`` is set; then read once more and close the driver."""
        next_read = time.monotonic()
        try:
            while not stop.is_set():
                self.heartbeat = time.monotonic()
                wait = next_read - self.heartbeat
                if wait > 0 and stop.wait(wait):
                    break
                next_read = self._step()
            if self._daq is not None and self.stats.connected:
                self._step()  # the scans made since the last read
        finally:
            self._flush_events()
            if self._daq is not None:
                self._daq.close()
                self._daq = None
            self.stats.connected = False

    def _step(self) -> float:
        """One read (connecting first if needed); returns the monotonic time of the next."""
        start = time.monotonic()
        if self._daq is None:
            try:
                self._daq = open_daq(self.url, timeout=self.timeout)
            except DAQError as exc:
                self._failed(exc, start)
                return start + self._next_backoff(start)
            self._connected(self._daq)
        daq = self._daq
        self.stats.read_starts.append(start)
        self.stats.reads += 1
        try:
            scans = daq.read_scans()
        except DAQError as exc:
            self._failed(exc, start)
            return start + self._next_backoff(start)
        if self._down_since is not None:
            self._recovered(start)
        self._backoff = BACKOFF_MIN_S
        # one driver for the acquisition's life (it reconnects itself): its count is ours
        self.stats.late_answers = getattr(daq, "late_fifo_answers", 0)
        new_epochs = {s.epoch for s in scans} - self._seen_driver_epochs
        if new_epochs and daq.has_fifo:
            self._sync_clock(daq)
        self._seen_driver_epochs |= new_epochs
        rows, taken = self._rows(scans)
        if daq.has_fifo:
            self._watch_foreign(rows, taken, daq.sequencer.taken_unreported)
        if len(rows) or self._pending_events:
            self._flush_events(rows)
        if daq.has_fifo:
            pacer = self.fifo_pacer
            pacer.rate_hz = self._rate_hz
        else:
            if self.poll_pacer is None or self.poll_pacer.rate_hz != self._rate_hz:
                self.poll_pacer = PollPacer(self._rate_hz)
            pacer = self.poll_pacer
        received = scans[-1].host_time if scans else time.monotonic()
        pacer.observe(start, received, scans)
        return pacer.next_read(time.monotonic())

    def _sync_clock(self, daq: DAQ) -> None:
        """Catch the moment a new scan appears (polling the latest scan for up to 1.5 scan
        periods), so that the first device-to-UTC offset of an epoch is not off by the age
        of the scan a FIFO read happened to be anchored on."""
        t_end = time.monotonic() + 1.5 / self._rate_hz
        try:
            prev = daq.snapshot()
            while time.monotonic() < t_end:
                time.sleep(0.002)
                snap = daq.snapshot()
                if snap.epoch != prev.epoch:
                    return
                if snap.counter64 != prev.counter64:
                    arrival = time.time_ns() + round((snap.host_time - time.monotonic()) * 1e9)
                    self._clock_hint = (snap.epoch, snap.host_time, arrival, snap.time64_us)
                    return
        except DAQError:
            return  # the next read reports it

    def _next_backoff(self, now: float) -> float:
        """Seconds to the next try: every BACKOFF_FAST_S through the restart window of an
        outage (a power-cycled module answers again within the datasheet's 2 s, and over
        ASCII every scan it makes before the first poll is lost), then doubling from
        BACKOFF_MIN_S to BACKOFF_MAX_S, or to a quarter of what the FIFO holds if that is
        less (1.28 s at 200 Hz: a link back after a long outage still finds its scans)."""
        if self._down_since is not None and now - self._down_since < RESTART_WINDOW_S:
            return BACKOFF_FAST_S
        cap = max(BACKOFF_MIN_S, min(BACKOFF_MAX_S, ldq412.FIFO_DEPTH / self._rate_hz / 4))
        wait = min(self._backoff, cap)
        self._backoff = min(cap, self._backoff * 2)
        return wait

    # ------------------------------------------------------------------ link state

    def _emit(self, kind: str, level: Level, message: str, **details: object) -> None:
        ev = Event(time.time_ns(), kind, level, message, dict(details))
        ev.log(log)
        self._pending_events.append(ev)

    def _flush_events(self, rows: np.ndarray | None = None) -> None:
        if rows is None:
            rows = np.zeros(0, dtype=SCAN_DTYPE)
        events, self._pending_events = self._pending_events, []
        if len(rows) or events:
            self.sink(Batch(rows, events, self.device))

    def _connected(self, daq: DAQ) -> None:
        ident = daq.identity
        rate = daq.scan_rate_hz
        self.device = DeviceInfo(
            daq.url, ident.model, ident.firmware, ident.serial, int(rate), daq.has_fifo
        )
        self._base_epoch = None
        if self.poll_pacer is not None:  # a new driver: epochs count from 0 again
            self.poll_pacer.reset()
        serial = "" if ident.serial is None else f", serial {ident.serial}"
        self._link_up(
            time.monotonic(),
            f"{ident.model} firmware {ident.firmware}{serial} at {daq.url}, {rate} Hz",
            daq.url,
            model=ident.model,
            firmware=ident.firmware,
            serial=ident.serial,
            scan_rate_hz=int(rate),
        )

    def _diagnose(self, exc: DAQError) -> Diagnosis:
        """Why the module is not reached, from the driver's error (no request is made)."""
        try:
            self.diagnosis = diagnose(exc, self.url, timeout=self.timeout)
        except Exception as err:  # noqa: BLE001 - a diagnosis never stops the acquisition
            log.debug("no diagnosis of %r: %r", exc, err)
            self.diagnosis = Diagnosis("error", f"{type(exc).__name__}: {exc}", "see the log")
        return self.diagnosis

    def _failed(self, exc: DAQError, now: float) -> None:
        self.stats.read_errors += 1
        self.stats.last_error = str(exc)
        if self._down_since is None:
            self._down_since = now
            self._down_logged = now
            self.stats.connected = False
            why = self._diagnose(exc)
            self._emit(
                "disconnect",
                Level.WARNING,
                f"{type(exc).__name__}: {exc}; why: {why.line()}",
                url=self.url,
                error=type(exc).__name__,
                cause=why.cause,
            )
            self._flush_events()
        elif now - self._down_logged >= self.report_every:
            self._down_logged = now
            log.warning("DAQ still unreachable after %.0f s: %s", now - self._down_since,
                        self._diagnose(exc).line())  # fmt: skip

    def _recovered(self, now: float) -> None:
        assert self._down_since is not None
        self._link_up(now, f"DAQ answers again after {now - self._down_since:.2f} s", self.url)

    def _link_up(self, now: float, message: str, url: str, **details: object) -> None:
        """The module answers (a new driver, or the same one after an outage): a ``connect``
        event, its details ending with ``outage_s``, the outage this ends at ``now``
        (monotonic s; None when the link was not down)."""
        outage = None if self._down_since is None else round(now - self._down_since, 3)
        self._down_since = None
        self.diagnosis = None
        self.stats.connected = True
        self._emit("connect", Level.INFO, message, url=url, **details, outage_s=outage)

    # ------------------------------------------------------------------ scans -> rows

    def _rows(self, scans: list[Scan]) -> tuple[np.ndarray, np.ndarray]:
        """The scans as rows, and per row whether another reader took its gap's scans."""
        if scans and self._base_epoch is None:
            scans = self._continue_from_last(scans)
        if not scans:
            return np.zeros(0, dtype=SCAN_DTYPE), np.zeros(0, dtype=bool)
        base = self._base_epoch
        assert base is not None
        n = len(scans)
        rows = np.zeros(n, dtype=SCAN_DTYPE)
        rows["counter64"] = [s.counter64 for s in scans]
        rows["time64_us"] = [s.time64_us for s in scans]
        rows["epoch"] = [base + s.epoch for s in scans]
        rows["missed"] = [s.missed for s in scans]
        rows["codes"] = [s.codes for s in scans]
        rows["status"] = [s.status for s in scans]
        rows["restarted"] = [s.restarted for s in scans]
        rows["overflow"] = [s.overflow for s in scans]
        rows["time_measured"] = [s.time_measured for s in scans]
        rows["status_measured"] = [s.status_measured for s in scans]
        rows["from_fifo"] = [s.source == "fifo" for s in scans]
        mono_ns, utc_ns = time.monotonic_ns(), time.time_ns()
        host = np.array([s.host_time for s in scans])
        rows["host_ns"] = utc_ns + np.round((host - mono_ns * 1e-9) * 1e9).astype(np.int64)
        resumed = self._first_missed is not None
        if resumed:
            rows["missed"][0] = self._first_missed
            self._first_missed = None
        self._stamp(rows, host)
        taken = np.array([s.taken for s in scans], dtype=bool)
        self._scan_events(rows, taken, first_ever=self._last is None, resumed=resumed)
        last = rows[-1]
        self._last = ResumePoint(
            int(last["epoch"]), int(last["counter64"]), int(last["time64_us"]),
            self.device.serial if self.device else None, self._floor,
        )  # fmt: skip
        self.stats.scans += n
        return rows, taken

    def _continue_from_last(self, scans: list[Scan]) -> list[Scan]:
        """First scans of a new driver: same power-on as the last recorded scan, or not?"""
        first = scans[0]
        last = self._last
        serial = self.device.serial if self.device else None
        if last is None:
            self._base_epoch = -first.epoch
            return scans
        if last.serial is not None and serial is not None and serial != last.serial:
            self._base_epoch = last.epoch + 1 - first.epoch
            self._emit("restart", Level.WARNING,
                       f"a different module answers (serial {serial}, was {last.serial}): "
                       "new epoch", epoch=last.epoch + 1, serial=serial)  # fmt: skip
            return scans
        if first.restarted or first.counter64 < last.counter64:
            self._base_epoch = last.epoch + 1 - first.epoch
            if not first.restarted:  # the restart flag is set on the first row below
                self._emit("restart", Level.WARNING,
                           "the module's counter went back while nobody read it: it restarted",
                           epoch=last.epoch + 1)  # fmt: skip
            return scans
        self._base_epoch = last.epoch - first.epoch
        # already recorded (a polled latest scan read again): drop
        scans = [s for s in scans if s.epoch != first.epoch or s.counter64 > last.counter64]
        if scans and scans[0].epoch == first.epoch:
            lost = scans[0].counter64 - last.counter64 - 1
            if lost > 0:
                self._first_missed = lost
        return scans

    def _stamp(self, rows: np.ndarray, host_s: np.ndarray) -> None:
        epochs = rows["epoch"]
        for e in np.unique(epochs):
            sel = epochs == e
            clock = self._clocks.get(int(e))
            if clock is None:  # older epochs are over; stamps go on after theirs
                self._clocks = {int(e): ClockMap(after=self._floor)}
                clock = self._clocks[int(e)]
            hint = self._clock_hint
            if hint is not None and hint[0] + (self._base_epoch or 0) == int(e):
                clock.observe(*self._clock_hint[1:])
                self._clock_hint = None
            idx = np.flatnonzero(sel)
            measured = idx[rows["time_measured"][idx]]
            i = measured[-1] if len(measured) else idx[-1]  # arrival was closest to the scan
            clock.observe(float(host_s[i]), int(rows["host_ns"][i]), int(rows["time64_us"][i]))
            rows["stamp_ns"][sel] = clock.stamps(rows["time64_us"][sel])
            self._floor = clock.floor

    def _scan_events(
        self, rows: np.ndarray, taken: np.ndarray, *, first_ever: bool, resumed: bool
    ) -> None:
        st = self.stats
        for i in np.flatnonzero(rows["missed"] | rows["restarted"] | rows["overflow"]):
            r = rows[i]
            c64, missed = int(r["counter64"]), int(r["missed"])
            if r["restarted"] and i == 0 and first_ever:
                text = "restart flag set at connect: powered on since it was last read"
                self._emit("restart", Level.INFO, f"the module's {text}",
                           epoch=int(r["epoch"]), counter64=c64)  # fmt: skip
            elif r["restarted"]:
                st.restarts += 1
                self._emit("restart", Level.WARNING,
                           f"module restarted (epoch {int(r['epoch'])}); {missed} scans of the "
                           "new power-on came before this one",
                           epoch=int(r["epoch"]), counter64=c64, missed=missed)  # fmt: skip
            elif missed:
                st.gaps += 1
                why, level = "counter gap", Level.WARNING
                if i == 0 and resumed:
                    why = "since the last recorded scan (read but not written, or never read)"
                elif taken[i]:  # the episode's warning says it once (_watch_foreign)
                    why, level = TAKEN_REASON, Level.INFO
                self._emit("gap", level,
                           f"{missed} scan(s) missed before counter {c64}: {why}",
                           missed=missed, counter64=c64, epoch=int(r["epoch"]),
                           reason=why)  # fmt: skip
            if r["overflow"] and first_ever:
                # a module nobody read fills its FIFO: what it dropped was never this
                # recorder's to lose, and the scans it kept open the recording
                self._emit("overflow", Level.INFO,
                           f"the module's FIFO was full when this recorder first read it "
                           f"(nobody had read it for {ldq412.FIFO_DEPTH / self._rate_hz:g} s "
                           f"or more): the recording begins with the {ldq412.FIFO_DEPTH} "
                           "scans it held; the older ones were dropped before the recorder "
                           "started", counter64=c64, at_connect=True)  # fmt: skip
            elif r["overflow"]:
                self._emit("overflow", Level.WARNING,
                           "the module's FIFO overflowed: its oldest scans were lost",
                           counter64=c64, at_connect=False)  # fmt: skip
            st.missed += missed
        status = rows["status"].astype(np.int64)
        rate = self._rate_hz
        for ch in range(4):
            self._flag_events("rail", self._rail[ch], ch, (status >> ch) & 1, rows, rate)
            self._flag_events("sensor_fault", self._fault[ch], ch, (status >> (4 + ch)) & 1,
                              rows, rate)  # fmt: skip

    def _watch_foreign(self, rows: np.ndarray, taken: np.ndarray, unreported: int) -> None:
        """Another reader of the module's FIFO: its episodes' events and counts."""
        for level, message, details in self._foreign.observe(rows, taken, self._rate_hz,
                                                             unreported):  # fmt: skip
            self._emit("foreign_reader", level, message, **details)
        ep = self._foreign.episode
        self.stats.foreign_taken = self._foreign.total
        self.stats.foreign_since_ns = None if ep is None else ep.since_ns

    def _flag_events(
        self, kind: str, flag: _Flag, ch: int, bits: np.ndarray, rows: np.ndarray, rate: int
    ) -> None:
        if not flag.on and not bits.any():
            return
        stamps = rows["stamp_ns"]
        clear_ns = round(FAULT_CLEAR_S * 1e9)
        what = "at the rail" if kind == "rail" else "sensor fault"
        for i in range(len(bits)):
            if bits[i]:
                flag.clear_since = None
                if not flag.on:
                    flag.on = True
                    self._emit(kind, Level.WARNING, f"channel {ch + 1} {what}",
                               channel=ch + 1, on=True, counter64=int(rows["counter64"][i]),
                               code=int(rows["codes"][i][ch]))  # fmt: skip
            elif flag.on:
                if flag.clear_since is None:
                    flag.clear_since = int(stamps[i])
                    flag.clear_counter = int(rows["counter64"][i])
                    flag.clear_epoch = int(rows["epoch"][i])
                if stamps[i] - flag.clear_since >= clear_ns:
                    # reported a second later, it names the first clear scan: where it ended
                    flag.on = False
                    flag.clear_since = None
                    c64, ep = flag.clear_counter, flag.clear_epoch
                    self._emit(kind, Level.INFO,
                               f"channel {ch + 1} no longer {what} from counter {c64}",
                               channel=ch + 1, on=False, counter64=c64, epoch=ep)  # fmt: skip
