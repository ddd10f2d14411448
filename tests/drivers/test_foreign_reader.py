"""Another Modbus master reading the module's FIFO: which gaps the sequencer puts down to it
(Scan.taken), and which to an overflow or a FIFO answer lost on the way.

The sequencer is driven by a model of the datasheet's FIFO (hypothesis draws the module's
scans, our reads, another master's reads and lost answers, and the model remembers who
removed each scan), then loopcal's Modbus TCP driver reads the emulated module while a
plain pymodbus client takes scans off its FIFO window.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopcal.drivers import Scan, ldq412, open_daq
from loopcal.drivers.sequence import RawSnapshot, Sequencer
from loopcal.simulator.clock import ManualClock
from loopcal.simulator.emulator import Emulator
from loopcal.simulator.open_points import OpenPoints
from tests.support.drivers import OK_TIMEOUT, PERIOD, RATE, check_against_truth, read_ok
from tests.support.foreign import FIFO_WINDOW, SCAN_REGS, ForeignReader
from tests.support.fuzz import examples
from tests.support.servers import modbus_tcp_relay

DEPTH = ldq412.FIFO_DEPTH
CHUNK = ldq412.FIFO_MAX_SCANS_PER_READ
CODES = (1, 2, 3, 4)


@dataclass
class Module:
    """The datasheet's FIFO, and who removed each scan from it: ``ours``, ``foreign``,
    ``lost`` (a read of ours whose answer never came) or ``dropped`` (an overflow).
    ``lag``: the snapshot is updated a moment before the scan is pushed into the FIFO, so
    a snapshot may count one scan the level does not (the datasheet leaves it open)."""

    lag: bool = False
    next: int = 0
    fifo: deque = field(default_factory=deque)
    overflow: bool = False
    fate: dict[int, str] = field(default_factory=dict)
    lost_reads: int = 0

    def make(self, n: int) -> None:
        for _ in range(n):
            if len(self.fifo) == DEPTH:
                self.fate[self.fifo.popleft()] = "dropped"
                self.overflow = True
            self.fifo.append(self.next)
            self.next += 1

    def snapshot(self) -> RawSnapshot:
        c = self.next - 1
        level = len(self.fifo) - (1 if self.lag and self.fifo else 0)
        status = ldq412.STATUS_OVERFLOW if self.overflow else 0
        return RawSnapshot(c, c * 50_000 % ldq412.U32_MOD, CODES, status, level)

    def pop(self, n: int, who: str) -> list[tuple[int, tuple[int, int, int, int]]]:
        out = []
        for _ in range(min(n, len(self.fifo))):
            c = self.fifo.popleft()
            self.fate[c] = who
            out.append((c, CODES))
        return out

    def gone_since(self, last: int, newest: int) -> list[str]:
        return [self.fate.get(c, "waiting") for c in range(last + 1, newest + 1)]


def drain(
    module: Module, seq: Sequencer, during: int = 0, lose_at: int | None = None, check=None
) -> list[Scan]:
    """Our read, as the Modbus driver makes it: the snapshot, then the waiting scans in
    chunks (the last asking for one more); ``during`` scans arrive before each chunk is
    read (a slow answer: the FIFO may overflow while it is read), and the ``lose_at``-th
    chunk's answer is lost on the way. ``check(snapshot)`` is called once the batch is
    begun."""
    snap = module.snapshot()
    seq.begin_batch(snap)
    if check is not None:
        check(snap)
    raw = []
    remaining = snap.fifo_level
    k = 0
    while remaining > 0:
        module.make(during)
        n = min(CHUNK, remaining + 1)
        if k == lose_at:
            module.pop(n, "lost")
            module.lost_reads += 1
            seq.fifo_read_lost()
            break
        chunk = module.pop(n, "ours")
        raw += chunk
        if len(chunk) < n:
            break
        remaining -= len(chunk)
        k += 1
    later = module.snapshot() if seq.gap_in(raw) else None  # as the driver reads one
    return seq.fifo_scans(raw, 0.0, later) if raw else []


OPS = st.one_of(
    st.tuples(st.just("make"), st.integers(0, 40)),
    st.tuples(st.just("make"), st.integers(240, 300)),  # an overflow, or nearly
    st.tuples(st.just("read"), st.integers(0, 3), st.none() | st.integers(0, 2)),
    st.tuples(st.just("read"), st.integers(0, 3) | st.integers(20, 300), st.none()),
    st.tuples(st.just("foreign"), st.integers(1, CHUNK)),
)


@pytest.mark.slow
@settings(max_examples=examples(300), deadline=None)
@given(first=st.integers(1, 300), ops=st.lists(OPS, min_size=1, max_size=40), lag=st.booleans())
def test_taken_only_for_gaps_another_master_made_and_always_for_them(first, ops, lag):
    """Every gap is put down to what really made it: never ``taken`` where an overflow
    dropped a scan or an answer of ours was lost, always where another master took every
    scan of the gap and the FIFO could not have overflowed; ``overflow`` wherever one
    dropped a scan; what the FIFO level shows taken before a gap is a lower bound (exact
    less the tolerated one)."""
    module, seq = Module(lag=lag), Sequencer(20)
    module.make(first)
    last: int | None = None
    taken_missed = 0
    bits: list[bool] = []  # the overflow bit at each of our anchors
    bit_at_last = False  # ... at the anchor of the batch that delivered ``last``
    for op in ops:
        if op[0] == "make":
            module.make(op[1])
            continue
        if op[0] == "foreign":
            module.pop(op[1], "foreign")
            continue
        _, during, lose_at = op

        def level_shows_no_more_than_was_taken(snap: RawSnapshot, last=last) -> None:
            bits.append(bool(snap.status & ldq412.STATUS_OVERFLOW))
            shown = seq.taken_unreported
            if shown:
                gone = module.gone_since(last, snap.counter)
                assert shown <= gone.count("foreign"), (shown, gone)

        scans = drain(module, seq, during, lose_at, level_shows_no_more_than_was_taken)
        newest = module.next - 1
        for s in scans:
            if last is not None:
                fates = set(module.gone_since(last, s.counter64 - 1))
                assert s.missed == s.counter64 - last - 1 and "ours" not in fates, (s, fates)
                if s.missed:
                    if "dropped" in fates:
                        assert s.overflow and not s.taken, (s, fates)
                    if s.taken:
                        assert fates == {"foreign"}, (s, fates)
                    elif fates == {"foreign"} and not module.lost_reads:
                        # an overflow could have dropped them, or the bit rose since the
                        # batch that delivered the last scan (an overflow while it was read)
                        rose = bits[-1] and not bit_at_last
                        assert newest - last >= DEPTH or rose, (s, last, newest)
            if s.taken:
                taken_missed += s.missed
            assert module.fate[s.counter64] == "ours"
            last, bit_at_last = s.counter64, bits[-1]
        assert seq.taken_total == taken_missed
        assert seq.fifo_reads_lost == module.lost_reads


@settings(max_examples=examples(200), deadline=None)
@given(
    made=st.integers(0, DEPTH + 10),
    taken=st.integers(0, 20),
    lag=st.booleans(),
    latched=st.booleans(),
)
def test_the_fifo_level_tells_scans_taken_before_a_gap_does(made, taken, lag, latched):
    module, seq = Module(lag=lag), Sequencer(20)
    module.make(1)
    module.overflow = latched  # an overflow long ago says nothing about this
    seq.begin_batch(module.snapshot())
    assert len(seq.fifo_scans(module.pop(2, "ours"), 0.0)) == 1
    module.make(made)
    module.pop(taken, "foreign")
    gone = min(taken, made)
    seq.begin_batch(module.snapshot())
    shown = seq.taken_unreported
    assert shown <= gone  # never more than were taken
    if not lag and made < DEPTH and module.overflow == latched:
        assert shown == max(0, gone - 1)  # the tolerated one less
    if not gone:
        assert shown == 0
    out = seq.fifo_scans(module.pop(made + 1, "ours"), 0.0)
    assert seq.taken_unreported == 0 or not out  # a scan delivered reports the gap
    if out and gone and made < DEPTH:
        assert out[0].taken and out[0].missed == gone and seq.taken_total == gone


def test_a_gap_while_the_overflow_bit_stays_latched_is_not_an_overflow():
    """The bit latches whenever the module sat unread long enough (at connect, normally):
    every later gap was marked an overflow, a foreign reader's too."""
    module, seq = Module(), Sequencer(20)
    module.make(300)  # unread since power-on: the FIFO overflowed
    first = drain(module, seq)
    assert first[0].overflow and len(first) == DEPTH and module.overflow
    module.make(10)
    module.pop(4, "foreign")
    [gap, *rest] = drain(module, seq)
    assert (
        gap.taken
        and gap.missed == 4
        and not gap.overflow
        and not any(s.overflow or s.taken or s.missed for s in rest)
    )
    module.make(DEPTH + 30)  # unread for longer than the FIFO holds: an overflow again
    [gap, *rest] = drain(module, seq)
    assert gap.overflow and not gap.taken and gap.missed == 30
    assert seq.taken_total == 4


def test_an_answer_lost_after_part_of_a_batch_is_not_another_masters():
    """The driver hands on the chunks read before a lost one (after it was told of the
    loss): their scans precede the loss, so the gap it leaves shows on the next batch."""
    module, seq = Module(), Sequencer(20)
    module.make(1)
    drain(module, seq)
    module.make(50)
    got = drain(module, seq, lose_at=1)  # the first chunk read, the second's answer lost
    assert len(got) == CHUNK and not any(s.missed for s in got)
    module.make(5)
    [gap, *_] = drain(module, seq)
    assert gap.missed == CHUNK and not gap.taken and not gap.overflow
    assert seq.taken_total == 0


# ---------------------------------------------------------------- against the emulator


def test_scans_another_master_takes_are_each_counted_once(emu_factory):
    """loopcal's driver and a plain pymodbus client read the same module's FIFO: every
    scan the other took is missed by loopcal, in a gap marked ``taken``, never overflow
    (though the overflow bit latched before loopcal's first read)."""
    emu, daq, clock = emu_factory("modbus-tcp")
    clock.advance(1.5)  # 300 scans at 200 Hz, unread: the FIFO overflowed
    got = read_ok(daq)
    assert got[0].overflow and len(got) == DEPTH
    with ForeignReader(emu.host, emu.port) as other:
        for k in range(30):
            clock.advance(0.05)  # 10 scans
            if k % 3 == 0:
                other.take(3 + k % 7)
            if k % 10 == 9:  # it takes every scan waiting: loopcal reads nothing
                other.take(CHUNK)
                assert read_ok(daq) == [] and daq.sequencer.taken_unreported > 0
                continue
            got += read_ok(daq)
        clock.advance(0.05)
        got += read_ok(daq)
        taken_by_other = set(other.counters)
    check_against_truth(got, emu)
    read = {s.counter64 for s in got}
    missing = set(range(got[0].counter64, got[-1].counter64)) - read
    assert missing == taken_by_other and len(taken_by_other) > 30
    assert sum(s.missed for s in got if s.taken) == len(missing) == daq.sequencer.taken_total
    assert all(s.taken for s in got if s.missed) and not any(s.overflow for s in got[1:])
    assert daq.sequencer.taken_unreported == 0


def test_a_fifo_the_driver_clears_itself_is_not_another_masters(emu_factory):
    emu, daq, clock = emu_factory("modbus-tcp")
    got = read_ok(daq)
    clock.advance(0.1)
    daq.clear_fifo()
    clock.advance(0.1)
    got += read_ok(daq)
    check_against_truth(got, emu)
    gaps = [s for s in got if s.missed]
    assert len(gaps) == 1 and gaps[0].missed == 20 and not gaps[0].taken
    assert daq.sequencer.taken_total == 0


@pytest.mark.parametrize("lagging", [False, True])
def test_the_level_tolerates_one_scan_not_yet_in_the_fifo(lagging):
    """A module that updates its snapshot before it pushes the scan into its FIFO shows a
    level one short with nothing taken: no scan is called taken for it."""
    module, seq = Module(lag=lagging), Sequencer(20)
    module.make(1)
    seq.begin_batch(module.snapshot())
    seq.fifo_scans(module.pop(1, "ours"), 0.0)
    for _ in range(20):
        module.make(7)
        seq.begin_batch(module.snapshot())
        assert seq.taken_unreported == 0
        out = seq.fifo_scans(module.pop(8, "ours"), 0.0)
        assert len(out) == 7 and not any(s.missed or s.taken for s in out)


def test_a_read_another_master_shortened_once_is_no_limit_of_the_module():
    """Another master takes 19 of 25 waiting scans between loopcal's snapshot and its FIFO
    read, on a module that answers an underrun short: the read gets 6 of the 20 asked
    while the snapshot said more wait. That is no read limit: the driver still reads 20
    scans a request (the finding: a power cycle between the two, under load, left it
    reading 6 at a time for good)."""
    clock = ManualClock()
    fifo_reads: list[int] = []  # scans each of loopcal's FIFO requests asked for
    other_takes = threading.Event()
    with (
        Emulator(
            "modbus-tcp",
            clock=clock,
            scan_rate_hz=RATE,
            open_points=OpenPoints(fifo_underrun="short"),
        ) as emu,  # fmt: skip
        ForeignReader(emu.host, emu.port) as other,
    ):

        def before(pdu: bytes) -> None:
            if pdu[0] == 4 and int.from_bytes(pdu[1:3], "big") == FIFO_WINDOW:
                fifo_reads.append(int.from_bytes(pdu[3:5], "big") // SCAN_REGS)
                if other_takes.is_set():
                    other_takes.clear()
                    assert len(other.take(19)) == 19

        with modbus_tcp_relay(emu.host, emu.port, before) as port:
            daq = open_daq(f"modbus-tcp://127.0.0.1:{port}", timeout=OK_TIMEOUT)
            try:
                got = read_ok(daq)
                clock.advance(25 * PERIOD)
                other_takes.set()
                fifo_reads.clear()
                got += read_ok(daq)
                assert fifo_reads == [20, 20]  # 6 answered, then none: the FIFO is empty
                clock.advance(45 * PERIOD)
                fifo_reads.clear()
                got += read_ok(daq)
                assert fifo_reads == [20, 20, 6] and daq.fifo_chunk == CHUNK
            finally:
                daq.close()
        check_against_truth(got, emu)
        taken = set(other.counters)
    assert len(taken) == 19 and taken.isdisjoint(s.counter64 for s in got)
    assert sum(s.missed for s in got if s.taken) == 19


def test_a_fifo_that_overflows_while_it_is_read_is_no_other_masters():
    """The module makes 300 scans between two FIFO reads of one batch (its answers slow):
    the FIFO overflows while it is read, and the scans it drops leave a gap that the
    batch's own counters cannot show to be a FIFO's length behind. Reported as an overflow,
    never as scans another master took (the finding: 136 scans put down to another master
    on a free-running clock with 300-400 ms answers, where no other master was)."""
    clock = ManualClock()
    fifo_reads = 0
    with Emulator("modbus-tcp", clock=clock, scan_rate_hz=RATE) as emu:

        def before(pdu: bytes) -> None:
            nonlocal fifo_reads
            if pdu[0] == 4 and int.from_bytes(pdu[1:3], "big") == FIFO_WINDOW:
                fifo_reads += 1
                if fifo_reads == 2:  # the batch's second chunk
                    clock.advance(300 * PERIOD)

        with modbus_tcp_relay(emu.host, emu.port, before) as port:
            daq = open_daq(f"modbus-tcp://127.0.0.1:{port}", timeout=OK_TIMEOUT)
            try:
                got = read_ok(daq)
                clock.advance(45 * PERIOD)
                fifo_reads = 0
                got += read_ok(daq)
                clock.advance(5 * PERIOD)
                got += read_ok(daq)
            finally:
                daq.close()
        check_against_truth(got, emu)
    [gap] = [s for s in got if s.missed]
    assert gap.overflow and not gap.taken and gap.missed == 45 - CHUNK + 300 - DEPTH
    assert daq.sequencer.taken_total == 0
