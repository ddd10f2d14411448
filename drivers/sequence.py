"""Turning raw device readings into a gap-free, unwrapped sequence of Scan records.

Pure logic, no I/O: every driver feeds it what it read, and it decides which scans are new,
how many were missed, where the device restarted, and what the 64-bit counter and time of
each scan are.

Two kinds of input:

* snapshots (registers 0..9 or the ``#AA`` answer): counter, time, codes, status of the
  latest scan, all measured. ``poll`` turns one into a Scan if its counter is new.
* FIFO scans (registers 256..): counter and codes only. ``begin_batch`` takes the snapshot
  read just before the FIFO as the *anchor*; ``fifo_scans`` then derives each FIFO scan's
  time as ``anchor time + (counter - anchor counter) x 1e6 / rate`` (rounded to the µs),
  which is exact whenever the scan period is a whole number of µs (1e6 % rate == 0) and
  within 1 µs otherwise. The FIFO scan whose counter equals the anchor's gets the
  anchor's measured time and status. Other FIFO scans get a derived status: rail bits
  computed from their own codes (datasheet: code 0 or 4095); fault bits = the fault bits
  of the anchor or of the previous anchor (the two snapshots bracketing the batch),
  restricted to channels reading 4095 (a faulted channel reads 4095, and a channel at 4095
  is untrustworthy anyway); latched bits 8-9 from the anchor.

Gaps in the FIFO: a FIFO scan after a counter gap (scans missed, no restart) has its gap
put down to one cause, the first of these that can explain it:

1. an overflow (``Scan.overflow``): the overflow bit rose since the last scan delivered,
   or the module made at least FIFO_DEPTH scans after that one (the newest counter known:
   the anchor's, the batch's newest FIFO scan's, or that of a snapshot read after the
   batch's FIFO reads, which the drivers read when the batch shows a gap
   (:meth:`Sequencer.gap_in`): a FIFO that overflows while it is read, its answers slow,
   drops scans that the batch's own counters cannot show to be that far behind). An
   overflow needs one scan more; the
   margin keeps a module that updates its registers a moment apart from being taken for
   another reader. The drivers never clear the overflow bit (clearing it also empties the
   FIFO, losing what arrived since the last read), so after the first overflow of a
   power-on it stays set and says nothing about later gaps. A scan is also marked
   ``overflow``, gap or not, when the bit rises (or is set at the first observation);
2. a FIFO answer lost on the way (``fifo_read_lost``): the scans that read took. No flag;
3. another reader of the FIFO window (``Scan.taken``, counted in ``taken_total``): the
   module kept the scans and no read of ours took them, so somebody else did.

The FIFO level tells the third before a gap shows it: all the scans made since the last
one delivered should wait in the FIFO, so at each anchor (the same power-on, fewer than
FIFO_DEPTH scans made, no answer lost since, the overflow bit not rising) a level lower by
more than one means scans were taken: at least that many less one (``taken_unreported``,
until a scan delivered reports the gap, exactly). One is tolerated: the datasheet leaves
open whether a module updates its snapshot before it pushes the scan into its FIFO.

Restart detection: the restart bit rising (or set at the first observation), the
counter going backwards (a backwards step of less than 2**31 is a restart; a larger one
is a 32-bit wrap), or, where the driver says when it sent each request (the ASCII
driver: its restart bit stays set), the host's clock: from the latest snapshot read to a
new one, both the device time and the counter (at the nominal rate) advanced less than the
host's clock by more than ``ANSWER_AGE_S`` + one period + ``CLOCK_TOLERANCE`` of the time
between them. The host time counted is the new request's sending (the module answered
after it, with a snapshot at most one period older, or ``ANSWER_AGE_S`` older for an
answer held on the way) and the old answer's arrival, so neither a slow answer nor a host
stopped while it waited looks like a restart. This rule sees a restart the other two
cannot: a power cycle during polls that failed until the counter came back past where it
was, the module on before it and off for longer than the allowance together. Taken
between successive snapshots, it holds for a module whose clock runs slower than the
host's (an emulator on its own clock, a replay slowed down) unless polls fail for long.
Each restart starts a new epoch with counter64 = the raw counter (the datasheet's
power-on counter starts at 0).
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from dataclasses import dataclass

from . import ldq412
from .records import Scan, ScanSource

U32 = ldq412.U32_MOD
HALF = U32 // 2
LATCHED_MASK = ldq412.STATUS_OVERFLOW | ldq412.STATUS_RESTART
#: scans the FIFO level may lag the counter by with none taken (module docstring)
LEVEL_TOLERANCE = 1
#: how much older than its request an answer's snapshot may be, s: the datasheet's module
#: answers within 10 ms, but on a loaded machine an emulator or a line (a pseudo-terminal,
#: a device server) has held an answer for 2.7 s (module docstring, restart detection)
ANSWER_AGE_S = 3.0
#: how far the module's clock may run from the host's, relative (0.005: 0.5 %)
CLOCK_TOLERANCE = 0.005


@dataclass(frozen=True, slots=True)
class RawSnapshot:
    """The latest scan as read from the device, every field raw (32-bit, wrapping).

    Attributes
    ----------
    counter : int
        Scan counter, 0..2**32-1.
    time_us : int
        Device time of channel 1's conversion, µs, 0..2**32-1.
    codes : tuple of 4 int
        Channel 1..4 ADC codes, 0..4095.
    status : int
        Status register (bits 0-3 rail, 4-7 fault, 8 overflow, 9 restart).
    fifo_level : int or None
        Scans waiting in the FIFO, 0..256 (Modbus input register 9); None over ASCII.
    """

    counter: int
    time_us: int
    codes: tuple[int, int, int, int]
    status: int
    fifo_level: int | None = None  # Modbus register 9; None over ASCII


@dataclass(frozen=True, slots=True)
class _Anchor:
    epoch: int
    counter: int
    counter64: int
    time_us: int
    time64: int
    status: int


@dataclass(frozen=True, slots=True)
class _ClockRef:
    """The power-on's latest snapshot read and when it arrived (the host-clock restart
    rule's reference, module docstring)."""

    arrived: float
    counter: int
    time_us: int


@dataclass(frozen=True, slots=True)
class _Last:
    epoch: int
    counter: int
    counter64: int


def signed_delta(value: int, ref: int) -> int:
    """The difference of two 32-bit wrapping counters.

    Parameters
    ----------
    value, ref : int
        Counters (or device times), 0..2**32-1.

    Returns
    -------
    int
        ``value - ref`` modulo 2**32, in [-2**31, 2**31).
    """
    return (value - ref + HALF) % U32 - HALF


def period_ticks_us(dcount: int, rate_hz: int) -> int:
    """The device time ``dcount`` scan periods take, in exact integer arithmetic.

    Parameters
    ----------
    dcount : int
        Scans (may be < 0).
    rate_hz : int
        Scan rate, Hz (> 0).

    Returns
    -------
    int
        ``round(dcount * 1e6 / rate_hz)`` µs, halves rounded up.
    """
    return (2 * dcount * 1_000_000 + rate_hz) // (2 * rate_hz)


def derived_status(codes: Sequence[int], anchor_status: int, other_fault: int = 0) -> int:
    """The status word of a FIFO scan, which the FIFO does not carry (module docstring).

    Parameters
    ----------
    codes : sequence of 4 int
        The scan's channel 1..4 codes, 0..4095.
    anchor_status : int
        The status of the snapshot the batch is anchored on.
    other_fault : int
        The status of the previous anchor (its fault bits count too).

    Returns
    -------
    int
        Rail bits 0-3 from the codes (0 or 4095), fault bits 4-7 of either anchor on
        channels reading 4095, latched bits 8-9 of ``anchor_status``.
    """
    rail = 0
    at_max = 0
    for i, code in enumerate(codes):
        if code == 0 or code == ldq412.CODE_MAX:
            rail |= 1 << i
        if code == ldq412.CODE_MAX:
            at_max |= 1 << i
    fault = (anchor_status | other_fault) & ldq412.STATUS_FAULT_MASK & (at_max << 4)
    return rail | fault | (anchor_status & LATCHED_MASK)


class Sequencer:
    """State that links successive reads of one device into one scan sequence: which
    scans are new, how many were missed, where the device restarted, and each scan's
    64-bit counter and time (module docstring). Every driver holds one
    (:attr:`loopcal.drivers.DAQ.sequencer`).

    Parameters
    ----------
    scan_rate_hz : int
        The module's scan rate, Hz (1..200), which derives FIFO scans' times.

    Attributes
    ----------
    scan_rate_hz : int
        The nominal scan rate in use, Hz.
    epoch : int
        Restarts detected so far (the epoch of the newest scan).
    restarts_detected : int
        Restarts detected so far (equal to ``epoch``).
    missed_total : int
        Scans missed over the sequence's life (the sum of Scan.missed).
    taken_total : int
        Of those, the scans another reader took off the FIFO (the sum of Scan.missed over
        the scans marked ``taken``).
    fifo_reads_lost : int
        FIFO reads given up on after they were sent, and FIFOs the driver emptied
        (:meth:`fifo_read_lost`): the scans each took are missing, counted in the
        ``missed`` of the next scan delivered.
    taken_unreported : int
        At least this many scans were taken by another reader, by the latest anchor's FIFO
        level, that no scan delivered has reported yet (0 when none; module docstring).
    measured_period_us : float or None
        The scan period measured between the latest two successive anchors of one epoch
        at least 20 scans apart, µs, or None (none yet, or the rate was set since).
    """

    def __init__(self, scan_rate_hz: int) -> None:
        self.scan_rate_hz = scan_rate_hz
        self.epoch = 0
        self.restarts_detected = 0
        self.missed_total = 0
        self.taken_total = 0
        self.fifo_reads_lost = 0
        self.taken_unreported = 0
        self._anchor: _Anchor | None = None
        self._prev_anchor: _Anchor | None = None  # newest anchor of the previous epoch
        self._batch_prev_anchor: _Anchor | None = None  # anchor before this batch's, same epoch
        self._last: _Last | None = None  # last scan delivered
        self._restart_bit_prev: bool | None = None
        self._clock_ref: _ClockRef | None = None
        self._first_restart = False  # restart bit was set when first observed
        self._pending_overflow = False
        self._overflow_bit_prev = False
        self._lost_read = False  # a FIFO answer was lost since the last delivered scan
        # ... during the batch under way: its scans come after everything the batch delivers
        self._lost_in_batch = False
        self._boundary_pending = False
        self._anchor_host_time: float | None = None
        # measured scan period (µs) between the last two anchors of one epoch, or None
        self.measured_period_us: float | None = None

    # -- bookkeeping ---------------------------------------------------------------

    def fifo_read_lost(self) -> None:
        """A FIFO read failed after it was sent (or the driver emptied the FIFO itself):
        the scans it took are lost, and the gap they leave after the scans this batch
        delivers is neither an overflow nor another reader's."""
        self.fifo_reads_lost += 1
        self._lost_in_batch = True

    def restart_bit_cleared(self) -> None:
        """The driver cleared the restart bit: the next time it is seen set is a restart."""
        self._restart_bit_prev = False

    @property
    def anchor_counter64(self) -> int | None:
        """counter64 of the newest snapshot (anchor) seen, or None before the first."""
        return None if self._anchor is None else self._anchor.counter64

    def _observe(self, snap: RawSnapshot, sent: float | None, arrived: float | None) -> bool:
        """Record a snapshot's restart evidence, and start a new epoch if it shows a new
        restart (module docstring); True if it did. ``sent``: when its request was sent,
        ``arrived``: when it arrived, ``time.monotonic()`` s (None: unknown)."""
        bit = bool(snap.status & ldq412.STATUS_RESTART)
        edge = bit and not self._restart_bit_prev
        self._restart_bit_prev = bit
        restarted = False
        if self._ref_counter() is None:
            self._first_restart = self._first_restart or edge
        elif edge or self.goes_back(snap.counter) or self._behind_host_clock(snap, sent):
            self._start_epoch()
            restarted = True
        self._note_clock(snap, arrived)
        return restarted

    def _elapsed(self, ref: _ClockRef, snap: RawSnapshot, host: float) -> tuple[float, int, int]:
        """From ``ref``'s arrival to ``host``: host s, device µs (its 32-bit wraps told by
        the host's clock) and scans from ``ref`` to ``snap``."""
        e = host - ref.arrived
        dt = (snap.time_us - ref.time_us) % U32
        dt += max(0, round((e * 1e6 - dt) / U32)) * U32
        return e, dt, signed_delta(snap.counter, ref.counter)

    def _behind_host_clock(self, snap: RawSnapshot, sent: float | None) -> bool:
        """The host-clock restart rule (module docstring)."""
        ref = self._clock_ref
        if ref is None or sent is None:
            return False
        e, dt_us, dc = self._elapsed(ref, snap, sent)
        allow = ANSWER_AGE_S + 1 / self.scan_rate_hz + CLOCK_TOLERANCE * e
        return dc >= 0 and e - dt_us / 1e6 > allow and e - dc / self.scan_rate_hz > allow

    def _note_clock(self, snap: RawSnapshot, arrived: float | None) -> None:
        """Make ``snap`` the clock reference (with a known arrival)."""
        if arrived is not None:
            self._clock_ref = _ClockRef(arrived, snap.counter, snap.time_us)

    def goes_back(self, counter: int) -> bool:
        """Whether a raw counter is behind the newest scan known of the current power-on:
        a restart (module docstring), or, over a link whose answers name no request, an
        earlier request's late answer.

        Parameters
        ----------
        counter : int
            Scan counter, 0..2**32-1.

        Returns
        -------
        bool
            True for a step back of less than 2**31 (a larger one is a 32-bit wrap);
            False before any scan is known.
        """
        ref = self._ref_counter()
        return ref is not None and (counter - ref) % U32 >= HALF

    def _ref_counter(self) -> int | None:
        """Raw counter of the newest scan known in the current epoch."""
        a, last = self._anchor, self._last
        if last is not None and last.epoch == self.epoch:
            if a is None or a.epoch != self.epoch or last.counter64 > a.counter64:
                return last.counter
        if a is not None and a.epoch == self.epoch:
            return a.counter
        return None

    def _start_epoch(self) -> None:
        self._prev_anchor = self._anchor
        self._clock_ref = None
        self.epoch += 1
        self.restarts_detected += 1

    def _set_anchor(self, snap: RawSnapshot) -> _Anchor:
        a = self._anchor
        if a is None or a.epoch != self.epoch:
            c64 = snap.counter  # assumes no 32-bit counter wrap before we connected
            nominal = period_ticks_us(c64, self.scan_rate_hz)
            wraps = max(0, round((nominal - snap.time_us) / U32))
            t64 = snap.time_us + wraps * U32
        else:
            dc = signed_delta(snap.counter, a.counter)
            c64 = a.counter64 + dc
            dt = (snap.time_us - a.time_us) % U32
            # Whole 32-bit time wraps between the anchors, from the counter (only matters
            # if two reads are more than 71.6 min apart).
            wraps = max(0, round((period_ticks_us(dc, self.scan_rate_hz) - dt) / U32))
            t64 = a.time64 + dt + wraps * U32
            if dc >= 20:
                self.measured_period_us = (t64 - a.time64) / dc
        anchor = _Anchor(self.epoch, snap.counter, c64, snap.time_us, t64, snap.status)
        self._anchor = anchor
        return anchor

    def period_mismatch(self, tolerance: float = CLOCK_TOLERANCE) -> bool:
        """Whether the measured scan period disagrees with the nominal rate (somebody
        changed the module's rate).

        Parameters
        ----------
        tolerance : float
            Relative disagreement allowed (0.005: 0.5 %).

        Returns
        -------
        bool
            False while no period has been measured.
        """
        p = self.measured_period_us
        nominal = 1e6 / self.scan_rate_hz
        return p is not None and abs(p - nominal) > tolerance * nominal

    def set_rate(self, hz: int) -> None:
        """A new nominal scan rate; the period measured at the old one is forgotten.

        Parameters
        ----------
        hz : int
            Scan rate, Hz (1..200).
        """
        self.scan_rate_hz = hz
        self.measured_period_us = None
        self._clock_ref = None  # its scans counted at the old rate

    def _deliver(self, epoch: int, counter: int, c64: int) -> tuple[int, bool, bool]:
        """Commit a delivered scan; returns (missed, restarted, overflow)."""
        last = self._last
        if last is not None and last.epoch == epoch:
            missed, restarted = c64 - last.counter64 - 1, False
        elif last is None and epoch == 0:
            missed, restarted = 0, self._first_restart
            self._first_restart = False
        else:
            missed, restarted = c64, True
        self._last = _Last(epoch, counter, c64)
        overflow, self._pending_overflow = self._pending_overflow, False
        self.missed_total += missed
        return missed, restarted, overflow

    # -- snapshot polling ----------------------------------------------------------

    def poll(
        self,
        snap: RawSnapshot,
        host_time: float,
        source: ScanSource = "snapshot",
        sent: float | None = None,
    ) -> tuple[Scan, bool]:
        """Feed one snapshot (a poll).

        Parameters
        ----------
        snap : RawSnapshot
            What the device answered.
        host_time : float
            ``time.monotonic()`` when the answer arrived, s.
        source : {"snapshot", "fifo"}
            Stored in the Scan.
        sent : float or None
            ``time.monotonic()`` when its request was sent, s: the host's clock then
            tells a restart that neither the restart bit nor the counter shows (module
            docstring). None: unknown.

        Returns
        -------
        tuple[Scan, bool]
            The scan and whether it is new; a counter already delivered gives False and a
            Scan with no events.
        """
        self._observe(snap, sent, host_time)
        a = self._set_anchor(snap)
        last = self._last
        is_new = last is None or last.epoch != a.epoch or a.counter64 > last.counter64
        missed, restarted, overflow = 0, False, False
        if is_new:
            missed, restarted, overflow = self._deliver(a.epoch, snap.counter, a.counter64)
        scan = Scan(
            counter=snap.counter,
            time_us=snap.time_us,
            codes=snap.codes,
            status=snap.status,
            counter64=a.counter64,
            time64_us=a.time64,
            epoch=a.epoch,
            missed=missed,
            restarted=restarted,
            overflow=overflow,
            time_measured=True,
            status_measured=True,
            source=source,
            host_time=host_time,
        )
        return scan, is_new

    def peek(self, snap: RawSnapshot, host_time: float, sent: float | None = None) -> Scan:
        """Like :meth:`poll`, without changing any state (a snapshot read beside the FIFO).

        Parameters
        ----------
        snap : RawSnapshot
            What the device answered.
        host_time : float
            ``time.monotonic()`` when the answer arrived, s.
        sent : float or None
            ``time.monotonic()`` when its request was sent, s (:meth:`poll`).

        Returns
        -------
        Scan
            The scan as :meth:`poll` would make it.
        """
        scan, _ = copy.deepcopy(self).poll(snap, host_time, sent=sent)
        return scan

    # -- FIFO ------------------------------------------------------------------------

    def begin_batch(
        self, snap: RawSnapshot, host_time: float | None = None, sent: float | None = None
    ) -> None:
        """Anchor the FIFO scans about to be read on the snapshot read just before.

        Parameters
        ----------
        snap : RawSnapshot
            The snapshot (input registers 0..9).
        host_time : float or None
            ``time.monotonic()`` when it arrived, s; the FIFO scan equal to it keeps it.
        sent : float or None
            ``time.monotonic()`` when its request was sent, s (:meth:`poll`).
        """
        self._anchor_host_time = host_time
        if self._lost_in_batch:  # lost in an earlier batch: its gap shows from this one on
            self._lost_read, self._lost_in_batch = True, False
        old = self._anchor
        if self._observe(snap, sent, host_time):
            self._boundary_pending = True
        anchor = self._set_anchor(snap)
        self._batch_prev_anchor = old if old is not None and old.epoch == self.epoch else None
        bit = bool(snap.status & ldq412.STATUS_OVERFLOW)
        if bit and not self._overflow_bit_prev:
            self._pending_overflow = True
        self._overflow_bit_prev = bit
        self.taken_unreported = self._taken_by_level(anchor, snap.fifo_level)

    def _taken_by_level(self, anchor: _Anchor, level: int | None) -> int:
        """Scans made since the last one delivered that the FIFO level says are gone, less
        the tolerance, where nothing of ours or the module's took them; else 0."""
        last = self._last
        if (level is None or last is None or last.epoch != anchor.epoch or self._lost_read
                or self._pending_overflow):  # fmt: skip
            return 0
        made = anchor.counter64 - last.counter64
        gone = made - level
        return gone - LEVEL_TOLERANCE if made < ldq412.FIFO_DEPTH and gone > LEVEL_TOLERANCE else 0

    def gap_in(self, raw: Sequence[tuple[int, tuple[int, int, int, int]]]) -> bool:
        """Whether FIFO scans read in this batch skip a counter, after the last scan
        delivered or between each other (a restart's step back is no gap).

        Parameters
        ----------
        raw : sequence of (int, tuple of 4 int)
            Raw counters and channel 1..4 codes, oldest first.

        Returns
        -------
        bool
            True if :meth:`fifo_scans` would report scans missed there; the driver then
            reads a snapshot for its ``later`` (module docstring, rule 1).
        """
        last = self._last
        prev = None if last is None or self._boundary_pending else last.counter
        for c, _ in raw:
            if prev is not None and 1 < (c - prev) % U32 < HALF:
                return True
            prev = c
        return False

    def fifo_scans(
        self,
        raw: Sequence[tuple[int, tuple[int, int, int, int]]],
        host_time: float,
        later: RawSnapshot | None = None,
    ) -> list[Scan]:
        """Turn the ``(counter, codes)`` pairs read from the FIFO into Scans.

        Scans that are not newer than the last delivered one (duplicates, stale data) are
        dropped. If the anchor showed a restart, the new epoch begins at the first scan
        whose counter goes backwards, or at the first scan if none does.

        Parameters
        ----------
        raw : sequence of (int, tuple of 4 int)
            Raw counters and channel 1..4 codes, oldest first.
        host_time : float
            ``time.monotonic()`` when the last FIFO answer arrived, s.
        later : RawSnapshot or None
            A snapshot read after the FIFO reads (when :meth:`gap_in`): its counter is the
            newest known for telling an overflow (ignored if it shows a restart the anchor
            did not). It anchors nothing.

        Returns
        -------
        list[Scan]
            The new scans, oldest first, ``source="fifo"``.

        Raises
        ------
        RuntimeError
            If no batch was begun (:meth:`begin_batch`).
        """
        anchor = self._anchor
        if anchor is None:
            raise RuntimeError("fifo_scans() before begin_batch()")
        boundary = -1  # scans before this index belong to the previous epoch
        if self._boundary_pending and raw:
            self._boundary_pending = False
            boundary = 0
            last = self._last
            prev = last.counter if last is not None and last.epoch == self.epoch - 1 else None
            if prev is not None and self._prev_anchor is not None:
                for i, (c, _) in enumerate(raw):
                    if (c - prev) % U32 >= HALF or c == prev:
                        boundary = i
                        break
                    prev = c
        resolved: list[tuple[_Anchor, int, int, tuple[int, int, int, int]]] = []
        newest: dict[int, int] = {}  # the newest counter64 known, per epoch
        for i, (c, codes) in enumerate(raw):
            a = anchor if i >= boundary else self._prev_anchor
            assert a is not None
            c64 = a.counter64 + signed_delta(c, a.counter)
            resolved.append((a, c64, c, codes))
            newest[a.epoch] = max(newest.get(a.epoch, a.counter64), c64)
        restart = ldq412.STATUS_RESTART
        if later is not None and (anchor.status & restart or not later.status & restart):
            ahead = signed_delta(later.counter, anchor.counter)
            newest[anchor.epoch] = max(newest.get(anchor.epoch, anchor.counter64),
                                       anchor.counter64 + ahead)  # fmt: skip
        rate = self.scan_rate_hz
        bracket = self._batch_prev_anchor
        other_fault = bracket.status if bracket is not None else 0
        out: list[Scan] = []
        for a, c64, c, codes in resolved:
            last = self._last
            if last is not None and (
                last.epoch > a.epoch or (last.epoch == a.epoch and c64 <= last.counter64)
            ):
                continue
            arrived = host_time
            if c64 == a.counter64:
                t64, status, measured = a.time64, a.status, True
                if a is anchor and self._anchor_host_time is not None:
                    arrived = self._anchor_host_time
            else:
                t64 = a.time64 + period_ticks_us(c64 - a.counter64, rate)
                extra = other_fault if a is anchor else 0
                status, measured = derived_status(codes, a.status, extra), False
            missed, restarted, overflow = self._deliver(a.epoch, c, c64)
            taken = False
            if missed and not restarted:  # the gap's cause (module docstring)
                if newest[a.epoch] - (c64 - missed - 1) >= ldq412.FIFO_DEPTH:
                    overflow = True
                elif not overflow and not self._lost_read:
                    taken = True
                    self.taken_total += missed
            self._lost_read = False
            self.taken_unreported = 0
            out.append(
                Scan(
                    counter=c,
                    time_us=t64 % U32,
                    codes=codes,
                    status=status,
                    counter64=c64,
                    time64_us=t64,
                    epoch=a.epoch,
                    missed=missed,
                    restarted=restarted,
                    overflow=overflow,
                    taken=taken,
                    time_measured=measured,
                    status_measured=measured,
                    source="fifo",
                    host_time=arrived,
                )
            )
        return out
