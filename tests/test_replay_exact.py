"""``loopcal replay`` serves the recorded scans themselves, on every transport: a recording
of the replay gives back exactly the original scans, whatever their phase, clock error,
wraps, gaps and restarts (the finding: a recording of an independent module, first scan
1809 µs after power-on, came back with every counter shifted by one and re-gridded times).
"""

from __future__ import annotations

import numpy as np
import pytest
from replay_helpers import (
    U32,
    assert_same_scans,
    finish,
    read_scans,
    replay_and_record,
    synthetic_rows,
    write_recording,
)

from simulator.clock import ManualClock  # noqa: F401 - the model below runs on it
from simulator.replay import FIRST_SCAN_LEAD_NS, RecordedModule, RecordedPowerOn

RATE = 50

pytestmark = pytest.mark.timeout(180)


def test_the_recorded_module_makes_exactly_the_recorded_scans():
    rows = synthetic_rows(RATE)
    from daemon.commands.replay import power_ons

    pos = power_ons(rows)
    assert [len(p.counter) for p in pos] == [80, 60, 80]
    module = RecordedModule(pos, rate_hz=RATE, now_ns=5)
    module.sync(10**12)
    first = [(t.counter, t.time_us) for t in module.truth]
    n0 = len(pos[0].counter)
    assert first == [
        (int(c) % U32, int(t) % U32) for c, t in zip(pos[0].counter, pos[0].time_us, strict=True)
    ]
    assert module.fifo_level == FIFO_OR_ALL(n0)
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


def FIFO_OR_ALL(n: int) -> int:  # noqa: N802 - reads as the quantity it is
    return min(n, 256)


def test_round_trip_on_every_transport(tmp_path):
    """All three transports at once (the serial ones phase-locked polling for ASCII at
    the recording's own pace; Modbus at twice it)."""
    rows = synthetic_rows(RATE)
    src = write_recording(tmp_path / "src", rows, RATE)
    runs = {
        t: replay_and_record(src, tmp_path / t, t, 1.0 if t == "ascii" else 2.0)
        for t in ("modbus-tcp", "modbus-rtu", "ascii")
    }
    for player, recorder in runs.values():
        finish(player, recorder)
    original = read_scans(src)
    for t in runs:
        again = read_scans(tmp_path / t)
        assert_same_scans(original, again)
