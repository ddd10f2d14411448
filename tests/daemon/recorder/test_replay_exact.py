"""``loopcal replay`` serves the recorded scans themselves, on every transport: a recording
of the replay gives back exactly the original scans, whatever their phase, clock error,
wraps, gaps and restarts (the finding: a recording of an independent module, first scan
1809 µs after power-on, came back with every counter shifted by one and re-gridded times).
"""

from __future__ import annotations

import numpy as np
import pytest

from loopcal.daemon.commands.replay import power_ons
from loopcal.drivers.ldq412 import FIFO_DEPTH
from loopcal.simulator.open_points import Latency, OpenPoints
from loopcal.simulator.replay import FIRST_SCAN_LEAD_NS, RecordedModule, RecordedPowerOn
from tests.support.processes import Proc, listening_url, record
from tests.support.recordings import read_scans, write_directory
from tests.support.replay import (
    assert_same_scans,
    finish,
    replay_and_record,
    replay_in_process,
)
from tests.support.rows import U32, synthetic_rows

RATE = 50

pytestmark = pytest.mark.timeout(180)


def test_the_recorded_module_makes_exactly_the_recorded_scans():
    rows = synthetic_rows(RATE)
    pos = power_ons(rows)
    assert [len(p.counter) for p in pos] == [80, 60, 80]
    module = RecordedModule(pos, rate_hz=RATE, now_ns=5)
    module.sync(10**12)
    first = [(t.counter, t.time_us) for t in module.truth]
    n0 = len(pos[0].counter)
    assert first == [
        (int(c) % U32, int(t) % U32) for c, t in zip(pos[0].counter, pos[0].time_us, strict=True)
    ]
    assert module.fifo_level == min(n0, FIFO_DEPTH)
    module.power_cycle(2.0)
    module.sync(10**12 + 2 * 10**9 + 699_999)
    assert not module.ready  # silent until its first scan, 700 µs after power-on
    module.sync(10**12 + 2 * 10**9 + 700_000)
    assert module.truth[-1].counter == 0 and module.truth[-1].time_us == 700
    module.sync(10**13)
    assert len(module.truth) == n0 + len(pos[1].counter)  # and nothing more until cycled
    module.power_cycle(2.0)
    module.sync(10**13 + 2 * 10**9 + FIRST_SCAN_LEAD_NS)  # one whose first scan came late
    assert module.truth[-1].counter == pos[2].counter[0] % U32 and module.ready
    with pytest.raises(ValueError):
        RecordedPowerOn(np.array([1, 1]), np.array([0, 1]), np.zeros((2, 4), int))


@pytest.mark.slow
def test_round_trip_on_every_transport(tmp_path):
    """All three transports at once: ASCII through ``loopcal replay`` at the recording's own
    pace (polled once per scan, phase-locked); Modbus at twice it, served by modules that
    answer as other makers' might (the emulator's open points): late and without filler
    scans, truncating long reads (TCP, set by ``loopcal replay``'s options); refusing them,
    answering across holes, only whole snapshots, with slow answers (RTU, in process)."""
    rows = synthetic_rows(RATE)
    src = write_directory(tmp_path / "src", rows, rate=RATE, per=25)
    original = read_scans(src)
    rtu = OpenPoints(latency=Latency(slow_fraction=0.02, slow_ms=(50.0, 70.0)),
                     max_read_registers=60, holes="zero", snapshot_reads="whole")  # fmt: skip
    runs = {
        "ascii": replay_and_record(src, tmp_path / "ascii", "ascii", 1.0),
        "modbus-tcp": replay_and_record(
            src,
            tmp_path / "tcp",
            "modbus-tcp",
            2.0,
            "--latency",
            "datasheet",
            "--fifo-underrun",
            "short",
            "--max-read-registers",
            "64",
            "--over-limit",
            "truncate",
        ),  # fmt: skip
        "modbus-rtu": replay_in_process(
            original, tmp_path / "rtu", "modbus-rtu", RATE, 2.0, open_points=rtu
        ),  # fmt: skip
    }
    for player, recorder in runs.values():
        finish(player, recorder)
    for t, out in (("ascii", "ascii"), ("modbus-tcp", "tcp"), ("modbus-rtu", "rtu")):
        try:
            assert_same_scans(original, read_scans(tmp_path / out), polled=t == "ascii")
        except AssertionError as exc:
            raise AssertionError(f"{t}: {exc}\n{runs[t][1].text}") from None
    with pytest.raises(ValueError, match="the recording's"):
        RecordedModule(power_ons(original), rate_hz=RATE, open_points=OpenPoints(clock_ppm=1))


def test_a_polled_recording_may_miss_a_scan_only_if_it_says_so():
    """The comparison for ASCII: a scan missing is allowed when the next one counts it, and
    only then; every other field must still be the original's."""
    rows = synthetic_rows(RATE)
    kept = np.delete(rows, 10).copy()
    kept["missed"][10] += 1  # declared by the next scan
    assert_same_scans(rows, kept, polled=True)
    silent = np.delete(rows, 10)
    with pytest.raises(AssertionError):
        assert_same_scans(rows, silent, polled=True)
    gap = int(np.flatnonzero(rows["missed"][1:80])[0]) + 1  # a scan after the original's gap
    after_gap = np.delete(rows, gap).copy()
    after_gap["missed"][gap] += 1 + rows["missed"][gap]  # the next counts both
    assert_same_scans(rows, after_gap, polled=True)
    after_gap["missed"][gap] -= rows["missed"][gap]
    with pytest.raises(AssertionError):
        assert_same_scans(rows, after_gap, polled=True)
    with pytest.raises(AssertionError):  # not polled: exact
        assert_same_scans(rows, kept)
    changed = kept.copy()
    changed["codes"][20, 0] ^= 1
    with pytest.raises(AssertionError):
        assert_same_scans(rows, changed, polled=True)
    second = rows["epoch"] == rows["epoch"][80]  # the second power-on, missing
    with pytest.raises(AssertionError, match="a power-on is missing"):
        assert_same_scans(rows, rows[~second], polled=True)


@pytest.mark.slow
def test_a_reader_slower_than_the_tail_still_gets_the_last_scans(tmp_path):
    """The replay ends 1 device second after the last scan (0.1 s of wall time at x10), and
    its module goes away with it: a recorder reading every 0.5 s lost what it had not read
    yet (once seen in a whole run on a loaded machine). The last scan is held, as each
    power-on's is, until the reader has taken it."""
    src = write_directory(tmp_path / "src", synthetic_rows(RATE), rate=RATE, per=25)
    player = Proc(["replay", str(src), "--transport", "modbus-tcp", "--speed", "10"])
    recorder = record(listening_url(player, timeout=30), tmp_path / "again",
                      "--read-period", "0.5")  # fmt: skip
    finish(player, recorder)
    assert_same_scans(read_scans(src), read_scans(tmp_path / "again"))


@pytest.mark.slow
def test_a_fifo_answer_held_back_is_not_cut_off_by_the_power_cycle(tmp_path):
    """Every answer 80 ms late (a module's latency, on purpose): the FIFO read that takes a
    power-on's last scans empties the FIFO when it arrives, and its answer leaves 80 ms
    later. The replay used to take the empty FIFO for the client's, power-cycle the module
    at once and close the connection with the answer in it (2 scans lost in a whole run on
    a loaded machine). It now waits for the client's next request."""
    rows = synthetic_rows(RATE)
    late = OpenPoints(latency=Latency(min_ms=80.0, max_ms=80.0))
    player, recorder = replay_in_process(
        rows, tmp_path / "again", "modbus-tcp", RATE, 2.0, open_points=late
    )
    finish(player, recorder)
    assert_same_scans(rows, read_scans(tmp_path / "again"))
