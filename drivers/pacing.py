"""When a scan stream (:meth:`loopcal.drivers.DAQ.scans`) reads the module next.

Pure logic, no I/O: the stream tells a pacer when each read was sent and answered and what
it brought, and asks when to send the next. Times are host ``time.monotonic()`` seconds.

With a FIFO (Modbus): a read every :data:`FIFO_READ_PERIOD_S`, as the daemon's default
``[daq].read_period``, and again at once after a read that found the FIFO half full or more
(the reader fell behind).

Without one (ASCII, or Modbus with ``fifo=0``): one poll per scan, at a safe point between
two scans. A poll returns the latest scan, so to read every scan once each poll must come
after scan k became readable and before scan k+1 did, with the answer time to spare. One
poll does not say where in the scan period it landed, so the pacer finds the scans'
*edge*: a search polls every ``step`` (a tenth of the period, 1 to 5 ms) until a new scan
appears; the last poll that still got the old scan (sent at ``s_old``) and the first that
got the new one (answered at ``r_new``) bracket the edge, ``s_old < edge <= r_new``. Every
other poll is sent ``target`` (0.4) of a period after the next predicted edge. The module's
clock is not the host's (±200 ppm moves a 20 Hz module's scans by 10 µs per period), so
the pacer searches again every ``research_scans`` (100) scans, 5 s at 20 Hz, in which a
clock 1000 ppm off moves the scans by a tenth of a period; at once after a poll that found
no new scan (too early) or skipped one (too late); and from scratch after a restart. A
search costs one or two polls more than the scans it reads.

The daemon's recorder phase-locks its polls in the same way, and fits the module's rate
against the host's clock too (:mod:`loopcal.daemon.recorder.polling`), which a stream read
for minutes has no need of.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from . import ldq412
from .records import Scan

#: s between two FIFO reads: 10 scans at 20 Hz, 100 at 200 Hz, inside the 256-scan FIFO
#: (1.28 s at 200 Hz). Each read is two Modbus transactions; twice a second costs a
#: controller less than half of five times a second (bench_daemon: 0.27 against 0.53 % of
#: a core for the recorder's acquisition thread), and what the reads feed waits longer
#: anyway (a recording flushes, the health monitor tests, every second). What it costs: the
#: time stamps' lower envelope has fewer samples (bench_stamps: median |stamp - true|
#: 3.2 ms against 2.2 ms at 0.2 s; a scan period is 50 ms).
FIFO_READ_PERIOD_S = 0.5


class FifoPacer:
    """A read every ``period_s``; at once after a read that found the FIFO half full.

    Parameters
    ----------
    period_s : float
        s between the starts of two reads (> 0).

    Raises
    ------
    ValueError
        If ``period_s`` is not > 0.
    """

    def __init__(self, period_s: float = FIFO_READ_PERIOD_S) -> None:
        if not period_s > 0:
            raise ValueError(f"FIFO read period must be > 0 s, got {period_s}")
        self.period_s = period_s
        self._next = -math.inf

    def observe(self, sent: float, received: float, scans: Sequence[Scan]) -> None:
        """Take note of one read.

        Parameters
        ----------
        sent, received : float
            When the read was sent and when its answer arrived, host monotonic s.
        scans : sequence of Scan
            What the read brought, oldest first (may be empty).
        """
        behind = len(scans) >= ldq412.FIFO_DEPTH // 2
        self._next = sent if behind else sent + self.period_s

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
        return max(now, self._next)


class PollPacer:
    """One poll per scan, phase-locked to the scans' edges (see the module docstring).

    Parameters
    ----------
    rate_hz : int
        The module's scan rate, Hz (1..200).
    target : float
        Where in the scan period a tracking poll is sent, as a fraction of the period after
        the predicted edge (0 < target < 1).
    research_scans : int
        Scans between two searches while tracking (>= 1).

    Raises
    ------
    ValueError
        If a parameter is out of its range.
    """

    def __init__(self, rate_hz: int, *, target: float = 0.4, research_scans: int = 100) -> None:
        if not ldq412.SCAN_RATE_MIN_HZ <= rate_hz <= ldq412.SCAN_RATE_MAX_HZ:
            raise ValueError(
                f"scan rate {rate_hz} Hz outside "
                f"{ldq412.SCAN_RATE_MIN_HZ}..{ldq412.SCAN_RATE_MAX_HZ}"
            )
        if not 0 < target < 1:
            raise ValueError(f"target {target} must be a fraction of the period (0..1)")
        if not research_scans >= 1:
            raise ValueError(f"research_scans must be >= 1, got {research_scans}")
        self.rate_hz = rate_hz
        self.period_s = 1 / rate_hz
        self.step_s = min(0.005, max(0.001, self.period_s / 10))
        self.target = target
        self.research_s = research_scans * self.period_s
        #: polls that found no new scan, and polls that skipped one (for tests)
        self.early = 0
        self.late = 0
        self.reset()

    def reset(self) -> None:
        """Forget the phase (a restart): search from scratch at the next poll."""
        #: host s at which the newest scan seen became readable (estimate), None: unknown
        self.edge: float | None = None
        self._last: tuple[int, int] | None = None  # (epoch, counter64) of the newest scan
        self._old_sent: float | None = None  # the latest poll of a search that found nothing
        self._searching = True
        self._lead = self.step_s  # how long before the predicted edge a search starts
        self._search_at = math.inf

    @property
    def locked(self) -> bool:
        """True while polls are sent once per scan (the edge is known, no search running)."""
        return self.edge is not None and not self._searching

    def observe(self, sent: float, received: float, scans: Sequence[Scan]) -> None:
        """Take note of one poll.

        Parameters
        ----------
        sent, received : float
            When the poll was sent and when its answer arrived, host monotonic s.
        scans : sequence of Scan
            The new scans the poll brought, oldest first (empty: the latest scan was
            already known).
        """
        if not scans:
            if self.locked:
                self.early += 1  # the edge came later than predicted: find it again
                self._searching = True
            self._old_sent = sent
            return
        newest = (scans[-1].epoch, scans[-1].counter64)
        last, self._last = self._last, newest
        old_sent, self._old_sent = self._old_sent, None
        if last is None or newest[0] != last[0]:
            self.reset()  # the first scan, or a restart: the scans' phase is new
            self._last = newest
            return
        ahead = newest[1] - last[1]
        if self.edge is not None:
            self.edge += ahead * self.period_s
        if self._searching:
            if old_sent is not None and ahead == 1 and received - old_sent < self.period_s:
                self.edge = 0.5 * (old_sent + received)  # bracketed
                self._searching = False
                self._lead = self.step_s
                self._search_at = received + self.research_s
            elif old_sent is None and self.edge is not None:
                self._lead = min(2 * self._lead, self.period_s / 2)  # started too late
        elif ahead > 1:
            self.late += 1  # sent on time and still past the next edge: find it again
            self._searching = True

    def next_read(self, now: float) -> float:
        """When to send the next poll.

        Parameters
        ----------
        now : float
            Host monotonic s.

        Returns
        -------
        float
            Host monotonic s, between ``now`` and one scan period later.
        """
        if self.edge is None:
            at = now + self.step_s  # nothing known yet: poll until an edge shows
        else:
            nxt = self.edge + self.period_s  # when the next scan becomes readable
            if not self._searching and now >= self._search_at:
                self._searching = True
            if not self._searching:
                at = nxt + self.target * self.period_s
            elif self._old_sent is None:
                at = nxt - self._lead  # a search starts just before the predicted edge
            else:
                at = now + self.step_s
        return min(max(at, now), now + self.period_s)
