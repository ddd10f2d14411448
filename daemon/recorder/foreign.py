"""Another Modbus master reading the module's FIFO: the episodes the acquisition reports.

The LDQ-412's FIFO gives each scan to whoever reads the FIFO window first, so a reader that
is not loopcal (a SCADA poll, a second host) cannot be locked out. The driver marks each
scan whose gap such a reader took (:attr:`loopcal.drivers.Scan.taken`: a gap that neither
an overflow nor a FIFO answer lost on the way explains) and counts what the FIFO level
shows gone before a gap does (:attr:`loopcal.drivers.sequence.Sequencer.taken_unreported`).
:class:`ForeignReaders` turns them into episodes: a ``foreign_reader`` warning when one
starts (since when, how many scans taken so far) and an info event when it ends, after
:data:`QUIET_S` of the module's own scans with nothing taken. The quiet stretch is counted
in scans, the module's clock, not the host's: a recorder that read nothing for a while (an
outage, a stop) has not seen the other reader stop. Every scan taken is a missed scan as
well: the rows and the gap events count it as any other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..events import Level
from ..times import time_or

#: s of the module's scans with nothing taken that end an episode
QUIET_S = 15.0

#: what :meth:`ForeignReaders.observe` asks the acquisition to raise: level, message, details
Notice = tuple[Level, str, dict[str, object]]


@dataclass
class Episode:
    """Another reader taking scans, from its first scan taken on.

    Attributes
    ----------
    since_ns : int
        UTC of the first scan taken, ns (between the stamps of the rows around it).
    counter64 : int
        That scan's counter.
    until_ns : int
        UTC of the last scan taken so far, ns.
    last_counter64 : int
        That scan's counter.
    taken : int
        Scans taken so far, as the gaps counted them.
    quiet : int
        Scans the module made since the last one taken.
    """

    since_ns: int
    counter64: int
    until_ns: int
    last_counter64: int
    taken: int = 0
    quiet: int = 0


class ForeignReaders:
    """The episodes of another reader of the module's FIFO (module docstring).

    Attributes
    ----------
    episode : Episode or None
        The episode under way.
    total : int
        Every scan taken since the acquisition started (the sum of the gaps put down to
        another reader).
    """

    def __init__(self) -> None:
        self.episode: Episode | None = None
        self.total = 0
        self._newest: tuple[int, int] | None = None  # (stamp_ns, counter64) of the last row

    def observe(
        self, rows: np.ndarray, taken: np.ndarray, rate_hz: int, unreported: int
    ) -> list[Notice]:
        """One read's rows: what starts or ends an episode.

        Parameters
        ----------
        rows : numpy.ndarray
            The read's scan rows (SCAN_DTYPE, oldest first), stamped.
        taken : numpy.ndarray of bool
            Per row, whether another reader took its gap's scans (``Scan.taken``).
        rate_hz : int
            The module's scan rate, Hz.
        unreported : int
            Scans the FIFO level shows taken that no gap has counted yet, at least (the
            driver's ``Sequencer.taken_unreported``).

        Returns
        -------
        list of Notice
            What the acquisition raises as ``foreign_reader`` events, in order.
        """
        out: list[Notice] = []
        period_ns = round(1e9 / rate_hz)
        if self.episode is not None or taken.any():
            quiet_scans = math.ceil(QUIET_S * rate_hz)
            prev = None if self._newest is None else self._newest[0]
            for r, by_other in zip(rows, taken, strict=True):
                missed, stamp, c64 = int(r["missed"]), int(r["stamp_ns"]), int(r["counter64"])
                # the scans taken lay evenly between the rows around the gap
                step = period_ns if prev is None else (stamp - prev) // (missed + 1)
                prev = stamp
                ep = self.episode
                if by_other:
                    first = ep is None
                    if ep is None:
                        ep = self.episode = Episode(stamp - missed * step, c64 - missed, 0, 0)
                    ep.taken += missed
                    ep.until_ns, ep.last_counter64, ep.quiet = stamp - step, c64 - 1, 0
                    self.total += missed
                    if first:
                        out.append(self._started(ep, ep.taken))
                elif ep is not None:
                    ep.quiet += 1 + missed
                    if ep.quiet >= quiet_scans:
                        out.append(self._ended(ep))
                        self.episode = None
        if len(rows):
            self._newest = int(rows["stamp_ns"][-1]), int(rows["counter64"][-1])
        if unreported and self.episode is not None:
            self.episode.quiet = 0
        elif unreported and self._newest is not None:
            # the level shows scans gone before a gap does: the oldest follow the newest row
            stamp, c64 = self._newest
            self.episode = Episode(stamp + period_ns, c64 + 1, stamp + period_ns, c64 + 1)
            out.append(self._started(self.episode, unreported, "at least "))
        return out

    @staticmethod
    def _started(ep: Episode, taken: int, at_least: str = "") -> Notice:
        return (
            Level.WARNING,
            f"another Modbus master is taking scans off the module's FIFO since "
            f"{time_or(ep.since_ns)}: {at_least}{taken} taken so far, each missing from the "
            "recording "
            "(loopcal cannot lock it out: find it and stop it)",
            {"since_ns": ep.since_ns, "taken": taken, "counter64": ep.counter64},
        )

    @staticmethod
    def _ended(ep: Episode) -> Notice:
        return (
            Level.INFO,
            f"another Modbus master took no scan off the module's FIFO for {QUIET_S:g} s of "
            f"its scans: {ep.taken} taken from {time_or(ep.since_ns)} until "
            f"{time_or(ep.until_ns)}",
            {"since_ns": ep.since_ns, "until_ns": ep.until_ns, "taken": ep.taken,
             "counter64": ep.last_counter64},
        )  # fmt: skip
