"""When to poll a module that has no FIFO (ASCII, or Modbus with ``fifo=0``): once per scan,
at a safe point between two scans, phase-locked to the module's own clock.

A poll returns the latest scan. To read every scan once, each poll must come after scan k
became readable and before scan k+1 did, with the answer time to spare. The module's clock
is not the host's (the datasheet says nothing of its accuracy: ±200 ppm moves a 20 Hz
module's scans by 10 µs per period, 0.7 s an hour), and one poll says nothing of where in
the period it landed. So the lock measures where the scans' edges are:

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
  late), and from scratch after a restart or reconnect (:meth:`reset`).

Times are host monotonic seconds; device times are the scans' unwrapped µs.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

#: prior standard deviation of the module's rate error (ppm / 1e6): loose, data dominate
RATE_PRIOR = 1e-3
#: a fitted rate error beyond this is not believed (a bracket went wrong)
RATE_LIMIT = 5e-3
BRACKETS_KEPT = 40
SEARCH_AFTER_LOCK_S = (0.5, 1.0, 2.0)


@dataclass(frozen=True)
class Bracket:
    """One measured edge: scan ``time_us`` became readable in (lo, hi] host seconds."""

    time_us: int
    lo: float
    hi: float


@dataclass
class PollStats:
    """What the lock did (for tests and the benchmark)."""

    polls: int = 0
    searches: int = 0
    early: int = 0  # polls that found no new scan
    late: int = 0  # polls sent on time that skipped a scan


class PhaseLock:
    """Poll schedule for one module at ``rate_hz`` (its nominal scan rate).

    Call :meth:`observe` after every poll with when it was sent and answered and what it
    found, then :meth:`next_poll` for when to send the next one.
    """

    def __init__(self, rate_hz: int, *, target: float = 0.4, research_s: float = 5.0) -> None:
        if not 0 < target < 1:
            raise ValueError(f"target {target} must be a fraction of the period")
        self.rate_hz = rate_hz
        self.period_us = 1_000_000 / rate_hz
        self.period_s = 1 / rate_hz
        self.step_s = min(0.005, max(0.001, 0.1 / rate_hz))
        self.target = target
        self.research_s = research_s
        self.stats = PollStats()
        self.reset()

    def reset(self) -> None:
        """Forget the phase (a restart, a reconnect): search again from the next poll."""
        self.brackets: collections.deque[Bracket] = collections.deque(maxlen=BRACKETS_KEPT)
        self._fit: tuple[float, float, int] | None = None  # (a, c, ref time_us)
        self._last_us: int | None = None  # device time of the newest scan seen
        self._old_sent: float | None = None  # the latest poll that found no new scan
        self._searching = True
        self._lead = self.step_s  # how early a search starts before the predicted edge
        self._search_at = 0.0
        self._after_lock = list(SEARCH_AFTER_LOCK_S)
        self._planned: float | None = None  # when a tracking poll was meant to leave

    @property
    def locked(self) -> bool:
        return self._fit is not None

    # ------------------------------------------------------------------ model

    def edge(self, time_us: float) -> float | None:
        """Predicted host time at which the scan of device time ``time_us`` is readable."""
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

    def observe(self, sent: float, received: float, newest_us: int | None, new: bool) -> None:
        """One poll: when it was sent and answered (host s), the device time of the newest
        scan known after it (None: none yet), and whether the poll brought that scan."""
        self.stats.polls += 1
        if newest_us is None:
            return
        if not new:
            if not self._searching:  # a tracking poll came before its scan
                self.stats.early += 1
                self._searching = True
            self._old_sent = sent
            return
        expected = None if self._last_us is None else self._last_us + self.period_us
        skipped = expected is not None and newest_us > expected + self.period_us / 2
        if self._searching:
            if self._old_sent is not None and not skipped and self._last_us is not None:
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

    def next_poll(self, now: float) -> float:
        """When to send the next poll (host s, between now and one period from now)."""
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
            at = nxt + self.target * self.period_s * (1 + self._fit[1])
            self._planned = max(at, now)
        return min(max(at, now), now + self.period_s)
