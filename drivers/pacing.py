"""When a reader of the module reads next: one pacer per way of reading, for the scan
stream (:meth:`loopcal.drivers.DAQ.scans`) and the daemon's acquisition alike.

Pure logic, no I/O: the reader tells a pacer (:class:`Pacer`) when each read was sent and
answered and what it brought, and asks when to send the next. Times are host
``time.monotonic()`` seconds; device times are the scans' unwrapped µs (``Scan.time64_us``).

With a FIFO (Modbus, :class:`FifoPacer`): a read every :data:`FIFO_READ_PERIOD_S` plus up
to one scan period, spread evenly over reads (golden-ratio steps: a period that is a whole
number of scan periods would find the latest scan at the same age read after read, and the
recorder's device-to-UTC map needs some reads just after a scan), and again at once after
a read that found the FIFO half full or more (the reader fell behind).

Without one (ASCII, or Modbus with ``fifo=0``, :class:`PollPacer`): one poll per scan, at a
safe point between two scans, phase-locked to the module's own clock. A poll returns the
latest scan, so to read every scan once each poll must come after scan k became readable
and before scan k+1 did, with the answer time to spare. The module's clock is not the
host's (the datasheet says nothing of its accuracy: ±200 ppm moves a 20 Hz module's scans
by 10 µs per period, 0.7 s an hour), and one poll says nothing of where in the period it
landed. So the pacer measures where the scans' edges are:

- a **search** polls every ``step`` (a tenth of the period, 1 to 5 ms) around the predicted
  edge until a new scan appears; the last poll that still got the old scan (sent at
  ``s_old``) and the first that got the new one (answered at ``r_new``) bracket the edge of
  that scan: ``s_old < edge <= r_new``. One search costs one or two polls more than the
  scans it reads;
- the edges' brackets, scan device time against host time, are fitted by a straight line
  (weighted least squares, its slope held near the nominal rate by a prior of ±1000 ppm
  that the data overrule within a minute): the module's phase and its rate against the
  host's clock;
- every other poll is sent ``target`` of the period (0.4) after the predicted edge: the
  furthest from both edges an answer of the datasheet's 10 ms allows at 20 Hz;
- searches come 0.5, 1, 2 s after locking, then every ``research_s`` (5 s), at once after
  a poll that found no new scan (too early) or skipped one although sent on time (too
  late), and from scratch after a restart (a scan of a new epoch) or :meth:`PollPacer.reset`
  (a reconnect).
"""

from __future__ import annotations

import collections
import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

from . import ldq412
from .records import Scan

#: s between two FIFO reads: 10 scans at 20 Hz, 100 at 200 Hz, inside the 256-scan FIFO
#: (1.28 s at 200 Hz). Each read is two Modbus transactions; twice a second costs a
#: controller less than half of five times a second (bench_daemon: 0.27 against 0.53 % of
#: a core for the recorder's acquisition thread), and what the reads feed waits longer
#: anyway (a recording flushes, the health monitor tests, every second). What it costs: the
#: time stamps' lower envelope has fewer samples (bench_stamps: the median stamp error
#: 2.9 ms against 2.2 ms at 0.2 s; a scan period is 50 ms).
FIFO_READ_PERIOD_S = 0.5
READ_DITHER_STEP = 0.6180339887498949  # golden ratio: even coverage of a scan period
#: prior standard deviation of the module's rate error (ppm / 1e6): loose, data dominate
RATE_PRIOR = 1e-3
#: a fitted rate error beyond this is not believed (a bracket went wrong)
RATE_LIMIT = 5e-3
BRACKETS_KEPT = 40
SEARCH_AFTER_LOCK_S = (0.5, 1.0, 2.0)


class Pacer(ABC):
    """When a reader of the module reads next: told of every read (:meth:`observe`),
    asked when to send the next (:meth:`next_read`).

    Attributes
    ----------
    rate_hz : int
        The module's scan rate the pacer works with, Hz.
    """

    rate_hz: int

    @abstractmethod
    def observe(self, sent: float, received: float, scans: Sequence[Scan]) -> None:
        """Take note of one read.

        Parameters
        ----------
        sent, received : float
            When the read was sent and when its answer arrived, host monotonic s.
        scans : sequence of Scan
            What the read brought, oldest first (may be empty).
        """

    @abstractmethod
    def next_read(self, now: float) -> float:
        """When to send the next read.

        Parameters
        ----------
        now : float
            Host monotonic s.

        Returns
        -------
        float
            Host monotonic s, ``now`` or later.
        """


class FifoPacer(Pacer):
    """A read every ``period_s`` plus a dither of up to one scan period; at once after a
    read that found the FIFO half full.

    Parameters
    ----------
    period_s : float
        s between the starts of two reads, before the dither (> 0).
    rate_hz : int
        The module's scan rate, Hz (the dither's span is one period); the reader sets
        :attr:`rate_hz` once it knows the module's.

    Raises
    ------
    ValueError
        If ``period_s`` is not > 0.
    """

    def __init__(self, period_s: float = FIFO_READ_PERIOD_S,
                 rate_hz: int = ldq412.SCAN_RATE_DEFAULT_HZ) -> None:  # fmt: skip
        if not period_s > 0:
            raise ValueError(f"FIFO read period must be > 0 s, got {period_s}")
        self.period_s = period_s
        self.rate_hz = rate_hz
        self.reads = 0
        self._next = -math.inf

    def observe(self, sent: float, received: float, scans: Sequence[Scan]) -> None:
        self.reads += 1
        behind = len(scans) >= ldq412.FIFO_DEPTH // 2
        self._next = sent if behind else sent + self.period_s + self.dither()

    def dither(self) -> float:
        """s added to the period after the latest read: 0 up to one scan period."""
        return (self.reads * READ_DITHER_STEP) % 1.0 / self.rate_hz

    def next_read(self, now: float) -> float:
        return max(now, self._next)


@dataclass(frozen=True)
class Bracket:
    """One measured edge of a scan.

    Attributes
    ----------
    time_us : int
        The scan's device time, µs.
    lo, hi : float
        It became readable in (lo, hi], host monotonic s: after the last poll that still
        got the scan before it was sent, at or before the first that got it was answered.
    """

    time_us: int
    lo: float
    hi: float


@dataclass
class PollStats:
    """What a :class:`PollPacer` did (for tests and the benchmark).

    Attributes
    ----------
    polls : int
        Polls observed.
    searches : int
        Searches that measured an edge.
    early : int
        Tracking polls that found no new scan (sent before its edge).
    late : int
        Polls sent when planned that skipped a scan (sent after the next edge).
    """

    polls: int = 0
    searches: int = 0
    early: int = 0
    late: int = 0


class PollPacer(Pacer):
    """One poll per scan, phase-locked to the module's clock (see the module docstring).

    Call :meth:`observe` after every poll with when it was sent and answered and the new
    scans it brought, then :meth:`next_read` for when to send the next one.

    Parameters
    ----------
    rate_hz : int
        The module's scan rate, Hz (1..200).
    target : float
        Where in the scan period a tracking poll is sent, as a fraction of the period after
        the predicted edge (0 < target < 1).
    research_s : float
        s between two searches while tracking, after the first three (> 0).

    Raises
    ------
    ValueError
        If a parameter is out of its range.
    """

    def __init__(self, rate_hz: int, *, target: float = 0.4, research_s: float = 5.0) -> None:
        if not ldq412.SCAN_RATE_MIN_HZ <= rate_hz <= ldq412.SCAN_RATE_MAX_HZ:
            raise ValueError(
                f"scan rate {rate_hz} Hz outside "
                f"{ldq412.SCAN_RATE_MIN_HZ}..{ldq412.SCAN_RATE_MAX_HZ}"
            )
        if not 0 < target < 1:
            raise ValueError(f"target {target} must be a fraction of the period (0..1)")
        if not research_s > 0:
            raise ValueError(f"research_s must be > 0 s, got {research_s}")
        self.rate_hz = rate_hz
        self.period_us = 1_000_000 / rate_hz
        self.period_s = 1 / rate_hz
        self.step_s = min(0.005, max(0.001, self.period_s / 10))
        self.target = target
        self.research_s = research_s
        self.stats = PollStats()
        self.reset()

    def reset(self) -> None:
        """Forget the phase (a restart, a reconnect): search again from the next poll."""
        self.brackets: collections.deque[Bracket] = collections.deque(maxlen=BRACKETS_KEPT)
        self._fit: tuple[float, float, int] | None = None  # (a, c, ref time_us)
        self._epoch: int | None = None  # the newest scan's epoch
        self._last_us: int | None = None  # device time of the newest scan seen
        self._old_sent: float | None = None  # the latest poll that found no new scan
        self._searching = True
        self._lead = self.step_s  # how early a search starts before the predicted edge
        self._search_at = 0.0
        self._after_lock = list(SEARCH_AFTER_LOCK_S)
        self._planned: float | None = None  # when a tracking poll was meant to leave

    @property
    def locked(self) -> bool:
        """True once an edge was measured (until a restart or :meth:`reset`)."""
        return self._fit is not None

    # ------------------------------------------------------------------ model

    def edge(self, time_us: float) -> float | None:
        """Predicted host time at which the scan of device time ``time_us`` is readable
        (None: not locked)."""
        if self._fit is None:
            return None
        a, c, ref = self._fit
        return a + (1 + c) * (time_us - ref) * 1e-6

    @property
    def rate_error(self) -> float | None:
        """The module's clock against the host's: +2e-4 is 200 ppm fast (None: no lock)."""
        return None if self._fit is None else 1 / (1 + self._fit[1]) - 1

    def _refit(self) -> None:
        ref = self.brackets[0].time_us
        s0 = s1 = s2 = sy = sxy = 0.0
        for b in self.brackets:
            x = (b.time_us - ref) * 1e-6
            y = 0.5 * (b.lo + b.hi) - x  # the offset, were the module's clock exact
            w = 1.0 / ((b.hi - b.lo) ** 2 / 12 + 1e-8)
            s0 += w
            s1 += w * x
            s2 += w * x * x
            sy += w * y
            sxy += w * x * y
        lam = 1 / RATE_PRIOR**2
        det = s0 * (s2 + lam) - s1 * s1
        a = (sy * (s2 + lam) - s1 * sxy) / det
        c = (s0 * sxy - s1 * sy) / det
        self._fit = (a, max(-RATE_LIMIT, min(RATE_LIMIT, c)), ref)

    # ------------------------------------------------------------------ polls

    def observe(self, sent: float, received: float, scans: Sequence[Scan]) -> None:
        """Take note of one poll (:meth:`Pacer.observe`): ``scans`` are the new scans it
        brought (empty: the latest scan was already known); a scan of another epoch than
        the last (a restart) starts the search from scratch."""
        self.stats.polls += 1
        if scans and scans[-1].epoch != self._epoch:
            if self._epoch is not None:
                self.reset()  # a restart: the scans' phase is new
            self._epoch = scans[-1].epoch
            self._last_us = scans[-1].time64_us
            return
        if self._last_us is None:
            return
        if not scans:
            if not self._searching:  # a tracking poll came before its scan
                self.stats.early += 1
                self._searching = True
            self._old_sent = sent
            return
        newest_us = scans[-1].time64_us
        expected = self._last_us + self.period_us
        skipped = newest_us > expected + self.period_us / 2
        if self._searching:
            if self._old_sent is not None and not skipped:
                if received - self._old_sent < self.period_s:  # the edge is bracketed
                    self.brackets.append(Bracket(newest_us, self._old_sent, received))
                    self._refit()
                    self._locked_again()
            elif self._old_sent is None and self._fit is not None:
                self._lead = min(2 * self._lead, self.period_s / 2)  # start earlier
        elif skipped and self._planned is not None and sent - self._planned < self.period_s / 4:
            self.stats.late += 1  # sent when planned, and still past the next edge
            self._searching = True
        self._old_sent = None
        self._last_us = newest_us

    def _locked_again(self) -> None:
        self._searching = False
        self._lead = self.step_s
        self.stats.searches += 1
        wait = self._after_lock.pop(0) if self._after_lock else self.research_s
        self._search_at = self.brackets[-1].hi + wait

    def next_read(self, now: float) -> float:
        """When to send the next poll (:meth:`Pacer.next_read`): at most one scan period
        after ``now``."""
        nxt = None if self._last_us is None else self.edge(self._last_us + self.period_us)
        if nxt is not None and not self._searching and now >= self._search_at:
            self._searching = True
        self._planned = None
        if nxt is None:
            at = now + self.step_s  # nothing known yet: poll until the edge shows
        elif self._searching:
            # just before the predicted edge, then every step until the new scan comes
            at = nxt - self._lead if self._old_sent is None else now + self.step_s
        else:
            assert self._fit is not None
            at = nxt + self.target * self.period_s * (1 + self._fit[1])
            self._planned = max(at, now)
        return min(max(at, now), now + self.period_s)
