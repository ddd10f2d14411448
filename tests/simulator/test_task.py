"""The operation scenario: the controller drives the plate round a fixed task loop, for ever
(simulator/task.py; ``loopcal simulate --scenario task``, the ldq412 fixture's ``"task"``)."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from loopcal.calibration.kinematics import base_points, output_axis_angles
from loopcal.calibration.parameters import NOMINAL, PRESETS
from loopcal.calibration.pipeline import calibrate
from loopcal.calibration.simulate import NEAR_SINGULAR_MM, perturbed_truth, reachable, readings
from loopcal.drivers import open_daq
from loopcal.simulator.scenarios import SCENARIOS, scenario_named
from loopcal.simulator.task import TaskLoop
from loopcal.simulator.testing import LDQ412Options
from tests.support.fuzz import examples
from tests.support.processes import Proc, listening_url, loopcal

SEEDS = (0, 1, 2, 7)


def _angular_velocity(loop: TaskLoop, t: np.ndarray, h: float = 1e-5) -> np.ndarray:
    """The plate's angular velocity (k, 3), rad/s, by a central difference of width 2h."""
    a, b = (Rotation.from_matrix(loop.rotation(t + d)) for d in (-h, h))
    return (b * a.inv()).as_rotvec() / (2 * h)


@pytest.mark.parametrize("seed", SEEDS)
def test_the_loop_repeats_exactly_and_starts_at_the_first_waypoint(seed):
    loop = TaskLoop(seed)
    assert loop.period_s == 5 * (2.0 + 0.5)
    t = np.random.default_rng(seed).uniform(0.0, 4 * loop.period_s, 3000)
    R = loop.rotation(t)
    for k in (1, 2, 50):
        assert np.abs(loop.rotation(t + k * loop.period_s) - R).max() <= 1e-12
    before = loop.rotation(np.array([-1e6, -3.0, -1e-9, 0.0]))
    assert np.abs(before - loop.orientations[0]).max() <= 1e-12
    assert np.isclose(loop.rotation(0.3)[0], loop.orientations[0], atol=1e-12).all()


@pytest.mark.parametrize("seed", SEEDS)
def test_the_plate_is_still_through_each_dwell_at_its_waypoint(seed):
    loop = TaskLoop(seed, waypoints=4, move_s=1.5, dwell_s=0.8)
    leg = 1.5 + 0.8
    for k in range(2 * loop.waypoints):  # two rounds
        held = loop.rotation(k * leg + np.linspace(0.0, 0.8 - 1e-6, 33))
        assert np.abs(held - held[0]).max() == 0.0  # identical rotations, not just close
        assert np.abs(held[0] - loop.orientations[k % loop.waypoints]).max() <= 1e-12
        moving = loop.rotation(k * leg + 0.8 + np.array([0.1, 0.75, 1.4]))
        assert np.abs(np.diff(moving, axis=0)).max() > 1e-3  # the moves move


@pytest.mark.parametrize("seed", SEEDS)
def test_every_orientation_is_reachable_by_the_mechanism(seed):
    truth = perturbed_truth(np.random.default_rng(seed))
    for params in (NOMINAL, truth):
        loop = TaskLoop(seed, params=params)
        R = loop.rotation(np.linspace(0.0, loop.period_s, 4000))
        # as the hand's moves are checked (tests/simulator/test_mechanism.py)
        assert reachable(R, params, margin_mm=9.0).all()
        assert reachable(loop.orientations, params, margin_mm=1.5 * NEAR_SINGULAR_MM).all()


def test_the_waypoints_are_the_seeds_whatever_order_the_times_are_asked_in():
    t = np.linspace(-2.0, 60.0, 700)
    a = TaskLoop(3).rotation(t)
    late_first = TaskLoop(3)
    order = np.random.default_rng(0).permutation(t.size)
    shuffled = late_first.rotation(t[order])
    b = np.empty_like(shuffled)
    b[order] = shuffled
    assert np.array_equal(a, b)
    again = TaskLoop(3)
    assert np.array_equal(a[350:], again.rotation(t[350:]))  # the later times first
    assert np.array_equal(a[:350], again.rotation(t[:350]))
    assert np.array_equal(TaskLoop(3).orientations, TaskLoop(3).orientations)
    assert not np.allclose(a, TaskLoop(4).rotation(t))
    assert TaskLoop(3).describe() == TaskLoop(3).describe()
    assert TaskLoop(3).describe() != TaskLoop(4).describe()


@pytest.mark.parametrize(("seed", "dwell_s"), [(0, 0.0), (1, 0.0), (2, 0.5)])
def test_moves_are_smooth_and_at_rest_at_each_waypoint(seed, dwell_s):
    loop = TaskLoop(seed, move_s=2.0, dwell_s=dwell_s)
    leg = 2.0 + dwell_s
    dt = 1e-3
    t = np.arange(0.0, loop.period_s + leg, dt)
    w = _angular_velocity(loop, t)
    speed = np.linalg.norm(w, axis=1)
    assert 0.3 < speed.max() < np.radians(120.0)  # it moves, at a controller's pace
    # continuous: from one ms to the next it changes by what a bounded acceleration allows
    # (a jump, at a waypoint or between two moves, would be of the order of the peak speed)
    assert np.linalg.norm(np.diff(w, axis=0), axis=1).max() < 0.02 * speed.max()
    # at rest when it reaches each waypoint and when it leaves it, dwell or none
    arrivals = np.arange(loop.waypoints + 1) * leg
    for at in np.concatenate([arrivals, arrivals + dwell_s]):
        assert np.linalg.norm(_angular_velocity(loop, np.array([at]), h=1e-4)) < 1e-4


@pytest.mark.parametrize("seed", SEEDS)
def test_the_loop_tilts_the_plate_toward_every_sensor(seed):
    loop = TaskLoop(seed)
    tilt, azimuth = output_axis_angles(loop.rotation(np.linspace(0.0, loop.period_s, 2000)))
    tilted = np.degrees(azimuth[np.degrees(tilt) > 15.0])
    quadrants = set(np.floor_divide(np.mod(tilted, 360.0), 90.0).astype(int))
    assert quadrants == {0, 1, 2, 3}
    A = base_points(NOMINAL)
    for sensor_deg in np.degrees(np.arctan2(A[:, 1], A[:, 0])):
        off = np.abs(np.angle(np.exp(1j * np.radians(tilted - sensor_deg))))
        assert np.degrees(off.min()) < 15.0, sensor_deg


@pytest.mark.parametrize("seed", [0, 2])
def test_two_minutes_of_the_loop_identify_lost_offsets_well_conditioned(seed):
    """The offsets are observable from the loop: two minutes of it at 20 Hz (every scan,
    moving or dwelling, with the sensors' noise and the 12-bit converter) identify the four
    offsets, the geometry known, with a well-conditioned selection and no problem."""
    truth = perturbed_truth(np.random.default_rng(seed + 10))
    start = truth.copy()
    start[16:20] = NOMINAL[16:20]  # the offsets lost: the blueprint's
    loop = TaskLoop(seed, params=truth)
    poses = readings(loop.rotation(np.arange(0.0, 120.0, 0.05)), truth, np.random.default_rng(1))
    cal = calibrate(poses.volts, PRESETS["offsets"], start)
    res = cal.identification
    assert res.problems() == []
    assert cal.selection.condition < 50.0  # CONDITION_OK is 1000
    assert np.all(res.std < 0.3)  # mm
    assert np.all(np.abs(res.params[16:20] - truth[16:20]) < 4 * res.std)
    assert np.abs(res.params[16:20] - truth[16:20]).max() < 0.6
    # the blueprint's offsets were millimetres off: the loop is what found them
    assert np.abs(start[16:20] - truth[16:20]).max() > 1.0


#: the hypothesis test's loops, one per setting (drawn once)
_LOOPS: dict[tuple, TaskLoop] = {}


@pytest.mark.slow
@settings(max_examples=examples(200), deadline=None, derandomize=True, database=None)
@given(st.lists(st.floats(-1e9, 1e9, allow_nan=False, allow_infinity=False),
                min_size=1, max_size=20),
       st.sampled_from([(2, 2.0, 0.5), (5, 2.0, 0.0), (3, 0.1, 7.0)]))  # fmt: skip
def test_any_finite_time_is_a_proper_rotation(times, setting):
    waypoints, move_s, dwell_s = setting
    loop = _LOOPS.setdefault(setting, TaskLoop(5, waypoints=waypoints, move_s=move_s,
                                               dwell_s=dwell_s))  # fmt: skip
    R = loop.rotation(np.array(times))
    assert R.shape == (len(times), 3, 3) and np.isfinite(R).all()
    assert np.abs(np.linalg.det(R) - 1.0).max() < 1e-12
    assert np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max() < 1e-12
    assert reachable(R, NOMINAL, margin_mm=9.0).all()


def test_bad_settings_are_refused_naming_the_problem():
    for kwargs, message in [
        ({"waypoints": 1}, "waypoints must be 2 or more, got 1"),
        ({"waypoints": 0}, "waypoints must be 2 or more"),
        ({"waypoints": 2.5}, "waypoints must be an integer, got 2.5"),
        ({"waypoints": True}, "waypoints must be an integer"),
        ({"move_s": 0.0}, "move_s must be a finite number, more than 0, got 0.0"),
        ({"move_s": -2.0}, "move_s must be"),
        ({"move_s": float("inf")}, "move_s must be a finite number"),
        ({"dwell_s": -0.1}, "dwell_s must be a finite number, 0 or more, got -0.1"),
        ({"dwell_s": float("nan")}, "dwell_s must be"),
        ({"max_tilt_deg": 95.0}, "max_tilt_deg must be under 90"),
    ]:
        with pytest.raises(ValueError, match=message):
            TaskLoop(0, **kwargs)
    assert TaskLoop(0, waypoints=np.int64(2), dwell_s=0).period_s == 4.0
    with pytest.raises(ValueError, match="times must be finite"):
        TaskLoop(0).rotation(np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="waypoints must be 2 or more"):
        scenario_named("task", waypoints=1)
    for option, message in [
        ({"task_waypoints": 1}, "ldq412 option task_waypoints=1: an integer, 2 or more"),
        ({"task_move_s": 0}, "ldq412 option task_move_s=0: seconds, > 0"),
        ({"task_dwell_s": -1.0}, "ldq412 option task_dwell_s=-1.0: seconds, >= 0"),
    ]:
        with pytest.raises(ValueError, match=message):
            LDQ412Options(scenario="task", **option)


@pytest.mark.slow
def test_loopcal_simulate_refuses_task_options_out_of_place_or_range():
    for args, message in [
        (["--task-dwell", "0"], "--task-dwell only with --scenario task, not --scenario hand"),
        (["--scenario", "static", "--task-waypoints", "3", "--task-move", "1"],
         "--task-waypoints, --task-move only with --scenario task, not --scenario static"),
        (["--scenario", "task", "--task-waypoints", "1"], "--task-waypoints must be 2 or more"),
        (["--scenario", "task", "--task-move", "0"], "--task-move must be a number of seconds"),
        (["--scenario", "task", "--task-dwell", "-1"], "--task-dwell must be 0 or more"),
    ]:  # fmt: skip
        proc = loopcal("simulate", "--duration", "1", *args, timeout=60)
        assert proc.returncode == 2, (args, proc.stderr)
        assert f"loopcal simulate: error: {message}" in proc.stderr, proc.stderr


def test_the_task_scenario_is_served_as_named():
    assert SCENARIOS["task"] is TaskLoop
    truth = perturbed_truth(np.random.default_rng(4))
    served = scenario_named("task", seed=4, params=truth, waypoints=3, move_s=1.0, dwell_s=0.0)
    same = TaskLoop(4, waypoints=3, move_s=1.0, dwell_s=0.0, params=truth)
    t = np.linspace(0.0, 10.0, 200)
    assert np.array_equal(served.rotation(t), same.rotation(t))
    assert served.describe()["period_s"] == 3.0 and served.describe()["name"] == "task"


@pytest.mark.ldq412(scenario="task", task_waypoints=3, task_move_s=1.0, task_dwell_s=0.0,
                    clock="manual", noise_volts=0.0, seed=6)  # fmt: skip
def test_the_fixture_serves_the_task_loop_round_and_round(ldq412):
    scenario = ldq412.truth.scenario
    assert scenario["name"] == "task" and scenario["waypoints"] == 3
    assert scenario["move_s"] == 1.0 and scenario["dwell_s"] == 0.0
    ldq412.advance(7.0)
    codes = np.array([s.codes for s in ldq412.scans])
    period = 60  # 3 s at 20 Hz: without noise, a round later the codes are the same
    assert len(codes) > 2 * period
    assert np.array_equal(codes[period:], codes[:-period])
    assert len({tuple(c) for c in codes[:period]}) > period // 2  # while it moves


@pytest.mark.slow
def test_loopcal_simulate_serves_the_task_loop_over_tcp():
    """``loopcal simulate --scenario task --task-dwell 0`` as a subprocess, read by a plain
    driver for 2 s of the emulator's own clock (its scans' stamps): the plate never stops,
    so the codes keep changing."""
    sim = Proc(["simulate", "--scenario", "task", "--task-dwell", "0", "--speed", "2",
                "--seed", "3"])  # fmt: skip
    try:
        url = listening_url(sim)
        assert url.startswith("modbus-tcp://127.0.0.1:")
        scans = []
        deadline = time.monotonic() + 20.0  # 1 s of real time at --speed 2, on a quiet machine
        with open_daq(url, timeout=2.0) as daq:
            while time.monotonic() < deadline:
                scans += daq.read_scans()
                if scans and scans[-1].time_us - scans[0].time_us >= 2_000_000:
                    break
                time.sleep(0.02)
        rc, _ = sim.stop()
    finally:
        sim.kill()
    assert rc == 0, sim.text
    assert scans and scans[-1].time_us - scans[0].time_us >= 2_000_000, len(scans)
    codes = np.array([s.codes for s in scans])
    assert len(codes) >= 30
    steps = np.abs(np.diff(codes, axis=0)).max(axis=1)
    assert (steps > 0).mean() > 0.9  # moving all the time: no dwell
    assert np.all(codes.max(axis=0) - codes.min(axis=0) > 20)  # every sensor sees the loop
