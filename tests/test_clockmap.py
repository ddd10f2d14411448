"""The recorder's time stamps with a module whose clock runs fast or slow
(daemon/recorder/clockmap.py), over simulated hours of FIFO reads with the datasheet's answer
times: monotonic, and within a few ms of when each scan was taken by the host's clock.
(bench/bench_stamps.py gives the figures over 6 hours against the former window minimum.)"""

from __future__ import annotations

import numpy as np
import pytest
from timeline_helpers import Module, datasheet_latency, run_stamps

from loopcal.daemon.recorder.clockmap import ClockMap


@pytest.mark.parametrize("ppm", [200.0, -200.0])
def test_stamps_follow_a_drifting_module_clock(ppm):
    run = run_stamps(
        ClockMap(), Module(ppm=ppm, phase_us=1809), 1.0, datasheet_latency(np.random.default_rng(4))
    )
    assert run.backwards == 0
    settled = run.errors_ms[20 * 60 :]  # after the first minute
    assert np.abs(settled).max() < 10, np.abs(settled).max()
    assert abs(np.median(settled)) < 4
    assert run.receive_ms.min() > -1.0  # never (or by under a ms) after the answer came


def test_a_host_clock_step_starts_over():
    cm = ClockMap()
    for k in range(100):
        cm.observe(0.0, 10**18 + k * 50_000_000 + 1_000_000, k * 50_000)
    before = int(cm.stamps(np.array([5_000_000]))[0])
    for k in range(100, 120):  # the host clock was set 3 s forward
        cm.observe(0.0, 10**18 + 3 * 10**9 + k * 50_000_000 + 1_000_000, k * 50_000)
    after = cm.stamps(np.array([6_000_000, 6_050_000]))
    assert before == 10**18 + 5 * 10**9 + 1_000_000
    assert after[0] == 10**18 + 3 * 10**9 + 6 * 10**9 + 1_000_000 and after[1] > after[0]
