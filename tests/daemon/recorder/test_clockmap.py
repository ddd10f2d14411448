"""The recorder's time stamps with a module whose clock runs fast or slow
(daemon/recorder/clockmap.py), over simulated hours of FIFO reads with the datasheet's answer
times: monotonic, and within a few ms of when each scan was taken by the host's clock;
an emulator at another speed followed too; and, whatever the answers say, never back.
(bench/bench_stamps.py gives the figures over 6 hours against the former window minimum.)"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopcal.daemon.recorder.clockmap import ClockMap
from tests.support.fuzz import examples
from tests.support.timeline import Module, datasheet_latency, run_stamps


@pytest.mark.slow
@pytest.mark.parametrize("ppm", [200.0, -200.0])
def test_stamps_follow_a_drifting_module_clock(ppm):
    run = run_stamps(
        ClockMap(), Module(ppm=ppm, phase_us=1809), 1.0, datasheet_latency(np.random.default_rng(4))
    )
    assert run.backwards == 0
    settled = run.errors_ms[20 * 60 :]  # after the first minute
    # reads every 0.5 s (FIFO_READ_PERIOD_S): the lower envelope has 20 samples a bin, and
    # the slope's first fits (the second minute) leave up to 11.6 ms here over seeds 4 to 6
    # (7.5 ms at 0.2 s, 5 reads a second): under a quarter of a scan period either way
    assert np.abs(settled).max() < 12.5, np.abs(settled).max()
    assert abs(np.median(settled)) < 4
    assert run.receive_ms.min() > -1.0  # never (or by under a ms) after the answer came


def test_a_host_clock_step_moves_the_line_with_it():
    """The host's clock set 3 s forward (UTC - monotonic steps by 3 s): what the map
    learnt moves with it, so the next stamps are the new UTC at once."""
    cm = ClockMap()
    for k in range(100):
        cm.observe(k * 0.05, 10**18 + k * 50_000_000 + 1_000_000, k * 50_000)
    before = int(cm.stamps(np.array([5_000_000]))[0])
    for k in range(100, 120):  # the host clock was set 3 s forward
        cm.observe(k * 0.05, 10**18 + 3 * 10**9 + k * 50_000_000 + 1_000_000, k * 50_000)
    after = cm.stamps(np.array([6_000_000, 6_050_000]))
    assert before == 10**18 + 5 * 10**9 + 1_000_000
    assert after[0] == 10**18 + 3 * 10**9 + 6 * 10**9 + 1_000_000 and after[1] > after[0]
    assert cm.host_steps == 1


def test_a_host_clock_set_back_steps_the_stamps_back_by_as_much():
    """Set 2 s back: the stamps step back by the 2 s (the recorder starts a new file
    there), not held at the floor for 2 s, and go on strictly increasing."""
    cm = ClockMap()
    for k in range(100):
        cm.observe(k * 0.05, 10**18 + k * 50_000_000 + 1_000_000, k * 50_000)
    first = cm.stamps(np.arange(100) * 50_000)
    for k in range(100, 140):
        cm.observe(k * 0.05, 10**18 - 2 * 10**9 + k * 50_000_000 + 1_000_000, k * 50_000)
    later = cm.stamps(np.arange(100, 140) * 50_000)
    assert int(later[0]) == int(first[-1]) + 50_000_000 - 2 * 10**9
    assert np.all(np.diff(later) == 50_000_000)


def test_a_new_power_on_carries_on_after_the_last_stamp():
    """A map for the next epoch starts from the last one's floor: its first stamp is after
    every stamp already handed on, even when its own line says earlier."""
    old = ClockMap()
    old.observe(1.0, 10**18 + 2 * 10**9, 1_000_000)
    s_old = old.stamps(np.array([1_000_000, 9_000_000]))  # the second stamped 8 s later
    new = ClockMap(after=old.floor)
    new.observe(2.0, 10**18 + 3 * 10**9, 0)  # its line: scan 0 at +3 s, before s_old[-1]
    s_new = new.stamps(np.array([0, 50_000]))
    assert int(s_new[0]) == int(s_old[-1]) + 1 and s_new[1] > s_new[0]


@pytest.mark.parametrize("speed", [0.5, 4.0, 10.0])
def test_stamps_follow_an_emulator_at_another_speed(speed):
    """An emulated module at --speed X has a clock X times as fast as the host's: far
    beyond any crystal, and what the demo records. Stamps follow it within the same few ms
    once the map has seen it move (1.5 s of samples, 3 s at 0.5), never go back, and the
    floor that keeps them in order holds almost none of them."""
    cm = ClockMap()
    raised = stamped = 0
    line_of = cm.line_stamps

    class Counting:
        def observe(self, *a):
            cm.observe(*a)

        def stamps(self, t):
            nonlocal raised, stamped
            line, s = line_of(t), cm.stamps(t)
            raised += int((s > line).sum())
            stamped += len(s)
            return s

    run = run_stamps(Counting(), Module(ppm=(speed - 1) * 1e6, phase_us=1809), 60 / 3600,
                     datasheet_latency(np.random.default_rng(4)))  # fmt: skip
    assert run.backwards == 0
    settled = np.abs(run.errors_ms[int(20 * speed * 5) :])  # after 5 s of host time
    assert settled.max() < 50, settled.max()
    assert np.median(settled) < 15, np.median(settled)
    assert raised <= stamped // 100, (raised, stamped)


# an answer: host monotonic s since the previous one, device µs the newest scan moved on,
# scans it carried, a step of the host's clock before it (0, or beyond 0.5 s either way),
# whether a hint of a newer scan is observed first (the acquisition's clock sync), and
# whether the module restarted before it (a new map from the last one's floor)
_answers = st.tuples(
    st.floats(0.0, 3.0),
    st.integers(1, 20_000_000),
    st.integers(1, 40),
    st.one_of(st.just(0), st.integers(600_000_000, 10**13), st.integers(-(10**13), -600_000_000)),
    st.booleans(),
    st.integers(0, 15).map(lambda x: x == 0),
)


@pytest.mark.slow
@settings(max_examples=examples(300), deadline=None)
@given(st.lists(_answers, min_size=1, max_size=120), st.integers(0, 10**17))
def test_stamps_never_go_back_whatever_the_answers(answers, utc0):
    """Adversarial arrivals: the module's clock anywhere from stopped to 10^7 times as fast
    as the host's and changing from one answer to the next, answers at the same instant,
    the host's clock set either way, restarts. Within the host's clock (its steps taken
    out) every stamp is strictly after every one before it, across maps."""
    cm = ClockMap()
    mono, dev, steps = 1.0, 0, 0
    prev: int | None = None
    for d_mono, d_dev, n, step, hint, restart in answers:
        if restart:
            cm, dev = ClockMap(after=cm.floor), 0
        mono += d_mono
        steps += step
        newest = dev + d_dev
        arrival = utc0 + steps + round(mono * 1e9)
        if hint:
            cm.observe(mono, arrival, newest + d_dev)
        cm.observe(mono, arrival, newest)
        times = np.unique(np.linspace(dev + 1, newest, n).astype(np.int64))
        s = cm.stamps(times)
        assert s.dtype == np.int64 and len(s) == len(times)
        own = s - steps  # the stamps with the host clock's steps taken out
        assert np.all(np.diff(own) > 0)
        if prev is not None:
            assert own[0] > prev
        prev = int(own[-1])
        dev = newest
