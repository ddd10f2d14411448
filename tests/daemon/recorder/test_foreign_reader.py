"""Another Modbus master reading the module's FIFO while loopcal records: one
``foreign_reader`` warning per episode and one event when it ends, every scan it took
counted as missed (and as taken, in the stats and the metrics), and nothing of the kind for
an overflow, a lost answer or an outage.

The acquisition runs in this process against the emulated module on 127.0.0.1, mostly on a
manual clock: the test decides how many scans the module makes and waits until loopcal has
read them, so what it asserts does not depend on how busy the machine is. The other master
is a plain pymodbus client (:mod:`tests.support.foreign`).
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from loopcal.daemon.events import Event, Level
from loopcal.daemon.recorder.acquisition import TAKEN_REASON, Acquisition, Batch
from loopcal.daemon.recorder.foreign import QUIET_S
from loopcal.daemon.scan_rows import SCAN_DTYPE
from loopcal.drivers.modbus import FIFO_ANSWER_WAIT_S
from loopcal.simulator.open_points import Latency
from loopcal.simulator.testing import EmulatedLDQ412
from tests.support.emulator import hand_emulator
from tests.support.foreign import ForeignReader
from tests.support.processes import free_port, record, scrape, value

pytestmark = pytest.mark.timeout(180)

RATE = 20
WAIT_S = 60.0  # a safety net only: each wait ends when what it waits for is seen


class Recording:
    """loopcal's acquisition reading ``module`` in a thread, and every batch it handed on."""

    def __init__(self, module: EmulatedLDQ412, **options) -> None:
        self.module = module
        self.batches: list[Batch] = []
        options.setdefault("read_period", 0.05)
        self.acq = Acquisition(module.url, self.batches.append, **options)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self.acq.run, args=(self._stop,), daemon=True)

    def __enter__(self) -> Recording:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(30)

    @property
    def rows(self) -> np.ndarray:
        rows = [b.rows for b in self.batches]
        return np.concatenate(rows) if rows else np.zeros(0, dtype=SCAN_DTYPE)

    def events(self, kind: str) -> list[Event]:
        return [e for b in self.batches for e in b.events if e.kind == kind]

    def until(self, what, why: str) -> None:
        deadline = time.monotonic() + WAIT_S
        while not what():
            assert time.monotonic() < deadline, f"{why}: not seen within {WAIT_S} s"
            time.sleep(0.01)

    def caught_up(self) -> None:
        """Wait until loopcal has recorded the module's newest scan."""
        newest = self.module.scans[-1].counter
        point = lambda: self.acq.resume_point  # noqa: E731
        self.until(lambda: point() is not None and point().counter64 == newest,
                   f"loopcal recording scan {newest}")  # fmt: skip

    def read_after_now(self) -> None:
        """Wait until a read of loopcal's begins after now (so the one under way ended)."""
        reads = self.acq.stats.reads
        self.until(lambda: self.acq.stats.reads > reads + 1, "two more reads")

    def fifo_level(self) -> int:
        with self.module.emulator.handle.synced() as device:
            return device.fifo_level


def missing(rows: np.ndarray) -> set[int]:
    """Counters between the first and the last row recorded that are not recorded."""
    c = rows["counter64"].astype(np.int64)
    return set(range(int(c[0]), int(c[-1]))) - set(c.tolist())


@pytest.mark.slow
def test_another_master_is_one_episode_and_every_scan_it_took_is_counted():
    """The module sat unread past its FIFO before loopcal connected (the overflow bit
    latched, as it normally is), then another master reads the FIFO window now and then:
    one warning when it starts, gaps at info that each name it, one event once the module
    has made 15 s of scans with nothing taken, and the scans it took are exactly the ones
    missing from the recording, counted as missed and as taken; none is called an
    overflow."""
    with EmulatedLDQ412(clock="manual", scenario="static", scan_rate_hz=RATE) as module:
        module.advance(14.0)  # 280 scans unread: the FIFO overflowed
        with (
            Recording(module, timeout=3.0) as rec,
            ForeignReader(module.emulator.host, module.port) as other,
        ):
            rec.caught_up()
            module.advance(0.5)
            rec.caught_up()
            assert not rec.events("foreign_reader") and rec.acq.stats.foreign_taken == 0
            # it takes every scan waiting: loopcal's next read finds the FIFO emptied
            module.advance(0.5)
            took = other.take(20)
            rec.read_after_now()
            by_level = len(took) >= 3 and took[-1] == module.scans[-1].counter
            if by_level:  # loopcal read none of them: the level told it first
                [start] = rec.events("foreign_reader")
                assert f"at least {len(took) - 1} taken so far" in start.message
                assert rec.acq.stats.foreign_active and rec.acq.stats.foreign_taken == 0
            for k in range(12):  # then a few of them every second of the module's scans
                module.advance(0.5)
                if k % 2:
                    other.take(3)
                module.advance(0.1)
                rec.caught_up()
            assert rec.acq.stats.foreign_active
            assert len(rec.events("foreign_reader")) == 1
            quiet = 0.0
            while quiet < QUIET_S + 1.0:  # nothing taken: the episode ends on the module's clock
                module.advance(0.5)
                quiet += 0.5
                rec.caught_up()
        rows = rec.rows
        stats = rec.acq.stats
    taken = set(other.counters)
    assert len(taken) >= 6 and missing(rows) == taken
    assert int(rows["missed"].sum()) == len(taken) == stats.foreign_taken == stats.missed
    assert not stats.foreign_active and stats.foreign_since_ns is None
    start, end = rec.events("foreign_reader")
    assert start.level == Level.WARNING and end.level == Level.INFO
    assert "another Modbus master is taking scans off the module's FIFO since" in start.message
    assert start.details["counter64"] == min(taken)
    assert start.details["since_ns"] == end.details["since_ns"] <= end.details["until_ns"]
    assert end.details["taken"] == len(taken) and end.details["counter64"] == max(taken)
    assert f"{len(taken)} taken from" in end.message
    # it began after the row before the first scan taken; told by a gap, before the row
    # after it too (told by the level, a period after the row before: on a manual clock the
    # stamps' floor may hold the rows closer than that)
    before = rows[rows["counter64"] < min(taken)][-1]
    after = rows[rows["counter64"] > min(taken)][0]
    assert before["stamp_ns"] <= start.details["since_ns"]
    assert by_level or start.details["since_ns"] <= after["stamp_ns"]
    gaps = rec.events("gap")
    assert gaps and all(g.level == Level.INFO and g.details["reason"] == TAKEN_REASON
                        for g in gaps)  # fmt: skip
    assert sum(g.details["missed"] for g in gaps) == len(taken)
    assert not rows["overflow"][1:].any() and len(rec.events("overflow")) == 1  # at connect


@pytest.mark.slow
def test_overflows_and_outages_are_not_another_master():
    """Left unread past its FIFO at connect and again later (a stall of 14 s at 20 Hz),
    and cut off for less than the FIFO holds: overflows and a link that came back, no
    foreign_reader event, nothing counted as taken."""
    with EmulatedLDQ412(clock="manual", scenario="static", scan_rate_hz=RATE) as module:
        module.advance(14.0)
        with Recording(module, timeout=3.0) as rec:
            rec.caught_up()
            module.advance(0.5)
            rec.caught_up()
            module.advance(14.0)  # 280 scans unread, the overflow bit still latched
            rec.caught_up()
            module.disconnect()
            rec.until(lambda: not rec.acq.stats.connected, "the link down")
            module.advance(5.0)  # 100 scans: the FIFO holds them
            module.reconnect()
            rec.caught_up()
            module.advance(0.5)
            rec.caught_up()
        rows = rec.rows
        stats = rec.acq.stats
    assert not rec.events("foreign_reader") and stats.foreign_taken == 0
    [gap] = rec.events("gap")
    assert gap.level == Level.WARNING and gap.details["missed"] == 280 - 256
    assert gap.details["reason"] != TAKEN_REASON
    assert len(rec.events("overflow")) == 2 and int(rows["overflow"].sum()) == 2
    # at connect the module had sat unread: not the recording's loss, said once as what it is
    at_connect, later = rec.events("overflow")
    assert at_connect.level == Level.INFO and at_connect.details["at_connect"]
    assert "full when this recorder first read it" in at_connect.message
    assert "begins with the 256 scans it held" in at_connect.message
    assert later.level == Level.WARNING and not later.details["at_connect"]
    assert "its oldest scans were lost" in later.message
    assert rec.events("disconnect") and len(missing(rows)) == 280 - 256


@pytest.mark.slow
def test_a_fifo_answer_lost_on_the_way_is_not_another_master():
    """Half the answers late past the FIFO read's wait (FIFO_ANSWER_WAIT_S): a FIFO read whose
    answer never came took its scans with it. The gap is loopcal's own loss, not another
    master's."""
    late_ms = FIFO_ANSWER_WAIT_S * 1000 + 200
    slow = Latency(min_ms=0.5, max_ms=1.0, slow_fraction=0.5, slow_ms=(late_ms, late_ms + 100))
    with EmulatedLDQ412(clock="manual", scenario="static", scan_rate_hz=RATE) as module:
        with Recording(module) as rec:
            rec.caught_up()
            module.faults.latency(slow)
            for _ in range(40):  # until a read's answer is lost (half of them are)
                module.advance(0.5)
                rec.until(lambda: rec.fifo_level() == 0, "the FIFO read")
                rec.read_after_now()
                recorded = rec.acq.resume_point
                if recorded is None or recorded.counter64 != module.scans[-1].counter:
                    break
            module.faults.latency(None)
            module.advance(0.5)
            rec.caught_up()
        rows = rec.rows
        stats = rec.acq.stats
    lost = missing(rows)
    assert lost and int(rows["missed"].sum()) == len(lost) == stats.missed
    assert not rec.events("foreign_reader") and stats.foreign_taken == 0
    gaps = rec.events("gap")
    assert gaps and all(g.level == Level.WARNING and g.details["reason"] != TAKEN_REASON
                        for g in gaps)  # fmt: skip
    assert not rows["overflow"].any()


@pytest.mark.slow
def test_the_metrics_count_what_another_master_took(tmp_path):
    """`loopcal record --metrics` while a plain Modbus client reads the FIFO window: the
    episode is on while it reads, off once the module made 15 s of scans without it, and
    the scans it took are counted (and logged once as a warning)."""
    port = free_port()
    with hand_emulator(speed=4.0) as emu, ForeignReader(emu.host, emu.port) as other:
        rec = record(emu.url, tmp_path / "rec", "--metrics", f"127.0.0.1:{port}",
                     "--timeout", "1")  # fmt: skip
        try:
            rec.wait_for("recording to", timeout=30)
            deadline = time.monotonic() + WAIT_S
            while value(m := scrape(port), "loopcal_daq_foreign_reader_active") == 0:
                assert time.monotonic() < deadline, rec.text
                other.take(20)
                time.sleep(0.1)
            assert value(m, "loopcal_daq_foreign_reader_scans_total") > 0
            assert value(m, "loopcal_events_total", kind="foreign_reader", level="warning") == 1
            while value(m := scrape(port), "loopcal_daq_foreign_reader_active") == 1:
                assert time.monotonic() < deadline + WAIT_S, rec.text
                time.sleep(0.2)
            rc, _ = rec.stop()
        finally:
            rec.kill()
    assert rc == 0, rec.text
    taken = value(m, "loopcal_daq_foreign_reader_scans_total")
    assert 0 < taken <= len(other.counters)
    # each scan it took, unless an answer of loopcal's own was lost in the same gap
    assert taken == len(other.counters) or value(m, "loopcal_daq_read_errors_total") > 0
    assert value(m, "loopcal_scans_missed_total") >= taken
    assert value(m, "loopcal_events_total", kind="foreign_reader", level="info") == 1
    assert rec.text.count("foreign_reader: another Modbus master is taking scans") == 1
