"""Loop-closure health: the daemon names the sensor whose offset moved (a step, a creep),
and stays quiet on clean data; the emulator's offset faults; the [health] settings."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import pytest

from loopcal.calibration.closure import drift_test, loop_closure, threshold
from loopcal.daemon.config.controller import nominal_config
from loopcal.daemon.live.health import HealthMonitor
from loopcal.daemon.recorder.settings import SettingsError, load_daemon_config
from loopcal.daemon.recording import read_recordings
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.run import FaultEvent
from loopcal.simulator.scenarios import HandMoves
from tests.support.emulator import hand_emulator
from tests.support.processes import NotifySocket, Proc, record, write_config
from tests.support.rows import rows_from
from tests.support.sessions import PAUSE_S, truth_for

pytestmark = pytest.mark.timeout(120)

TRUTH = truth_for(3)


def monitor_run(drifts, seconds, *, seed=3, truth=TRUTH):
    """Feed an offline session to a monitor a quarter second at a time; returns the monitor
    and the events as (device time s, kind, details)."""
    scenario = HandMoves(seed, params=truth, pause_s=PAUSE_S)
    t_us, codes = mechanism_scans(
        scenario, truth, 20 * seconds, noise_volts=0.04, seed=seed, drifts=drifts
    )
    rows = rows_from(t_us, codes)
    events = []
    clock = [0.0]
    mon = HealthMonitor(
        replace(nominal_config(), params=tuple(truth)),
        lambda kind, level, msg, **d: events.append((clock[0], kind, d)),
    )
    for a in range(0, len(rows), 5):
        clock[0] = t_us[min(a + 4, len(rows) - 1)] / 1e6
        mon.feed(rows[a : a + 5])
    return mon, events


@pytest.mark.slow
def test_clean_data_raises_nothing():
    mon, events = monitor_run((), 900)
    assert mon.state.poses > 250 and events == []
    assert "loops close" in mon.status()
    # the loop-closure errors at the truth are N(0, 1): the noise model is right
    assert 0.7 < mon.state.last.chi2_rms < 1.3  # RMS of 30: +- 0.13


@pytest.mark.slow
@pytest.mark.parametrize("sensor", [1, 2, 3, 4])
@pytest.mark.parametrize(("kind", "amount"), [("step", 0.5), ("creep", 1.0)])
def test_a_moved_offset_is_attributed_to_its_sensor(sensor, kind, amount):
    at = 120.0
    mon, events = monitor_run((OffsetDrift(kind, sensor, at, amount),), 360)
    alarms = [(t, d) for t, k, d in events if k == "offset_drift"]
    assert alarms, f"no alarm for a {kind} on sensor {sensor}"
    t, d = alarms[0]
    assert d["sensor"] == sensor, alarms
    assert 0 < t - at < 90, t - at
    shift = amount if kind == "step" else amount * (t - at) / 60
    # a step is estimated as a step, a creep as a creep (its shift at the latest pose)
    assert d["shape"] == kind, d
    assert abs(d["shift_mm"] - shift) < (0.15 if kind == "step" else 0.25), (d, shift)
    assert all(d2["sensor"] == sensor for _, d2 in alarms)
    assert f"OFFSET DRIFT sensor {sensor}" in mon.status()


@pytest.mark.slow
def test_a_step_that_goes_away_is_cleared():
    drift = OffsetDrift("step", 2, 60.0, 0.8, duration=90.0)
    _, events = monitor_run((drift,), 420)
    kinds = [k for _, k, _ in events]
    assert kinds[:2] == ["offset_drift", "offset_drift_cleared"], events


def test_the_threshold_holds_its_false_alarm_rate():
    """Pure noise at the truth: the largest of the four statistics over 30 poses exceeds
    the 1 % threshold about 1 % of the time (Bonferroni: at most)."""
    rng = np.random.default_rng(0)
    from loopcal.calibration.implicit import predicted_volts
    from loopcal.calibration.simulate import sample_workspace

    R = sample_workspace(3000, rng, TRUTH)
    clean = predicted_volts(R, TRUTH)
    sigma = 0.04 / np.sqrt(20)
    V = clean + rng.normal(0, sigma, clean.shape)
    cl = loop_closure(V, TRUTH, np.full(4, sigma))
    assert 0.95 < np.sqrt(np.mean(cl.error**2)) < 1.05
    gamma = threshold(0.01)
    hits = 0
    for k in range(0, 3000, 30):
        sl = slice(k, k + 30)
        sub = type(cl)(cl.error[sl], cl.offset_pattern[sl], cl.information[sl], cl.usable[sl])
        hits += drift_test(sub).statistic.max() > gamma
    assert hits <= 4  # 100 windows at <= 1 %


def test_offset_faults_parse_and_are_drifts():
    e = FaultEvent.parse("offset@30:3=+0.5")
    assert e.drift() == OffsetDrift("step", 3, 30.0, 0.5)
    e = FaultEvent.parse("creep@10+60:2=1.5")
    assert e.drift() == OffsetDrift("creep", 2, 10.0, 1.5, 60.0)
    d = e.drift()
    assert np.allclose(d.shift_mm(np.array([0.0, 10.0, 40.0, 70.0, 500.0])),
                       [0.0, 0.0, 0.75, 1.5, 1.5])  # fmt: skip
    for bad, msg in [("offset@30:5=1", "channel 1..4"), ("offset@30:2=x", "AMOUNT in mm"),
                     ("creep@30:2", "AMOUNT in mm per minute")]:  # fmt: skip
        with pytest.raises(ValueError, match=msg):
            FaultEvent.parse(bad)


@pytest.mark.slow
def test_simulate_refuses_a_drift_on_a_replay(tmp_path):
    p = Proc(["simulate", "--scenario", "replay", "--replay", str(tmp_path / "x.jsonl"),
              "--fault", "offset@3:1=0.5"])  # fmt: skip
    assert p.wait(30) == 2
    assert "need a simulated mechanism" in "\n".join(p.lines)


def test_health_settings_are_checked(tmp_path):
    cfg = write_config(tmp_path / "d.toml", "modbus-tcp://127.0.0.1:5020", tmp_path,
                       "\n[health]\nenabled = false\nfalse_alarm = 1e-6\n")  # fmt: skip
    s = load_daemon_config(cfg)
    assert s.health is False and s.health_false_alarm == 1e-6
    for extra, msg in [("enabled = 1", r"\[health\].enabled: must be true or false"),
                       ("false_alarm = 0.5", r"\[health\].false_alarm: must be a probability"),
                       ("window = 3", r"\[health\].window: unknown key")]:  # fmt: skip
        write_config(cfg, "modbus-tcp://127.0.0.1:5020", tmp_path, f"\n[health]\n{extra}\n")
        with pytest.raises(SettingsError, match=msg):
            load_daemon_config(cfg)


@pytest.mark.slow
def test_the_daemon_raises_offset_drift_in_events_log_and_status(tmp_path):
    """An emulated module whose sensor 2 core slips 0.8 mm after 20 s of device time: the
    daemon's event names sensor 2, in the MCAP events, the log and the STATUS line."""
    controller = tmp_path / "controller.toml"
    init = Proc(["init-config", str(controller)])
    assert init.wait(60) == 0
    drift = (OffsetDrift("step", 2, 20.0, 0.8),)
    out = tmp_path / "rec"
    with hand_emulator(rate=20, speed=10.0, seed=5, drifts=drift) as emu:
        cfg = write_config(tmp_path / "daemon.toml", emu.url, out,
                           f'\n[controller]\nconfig = "{controller}"\n')  # fmt: skip
        notify = NotifySocket(tmp_path / "notify.sock")
        daemon = Proc(["daemon", "--config", str(cfg)], env={"NOTIFY_SOCKET": str(notify.path)})
        try:
            line = daemon.lines[daemon.wait_for(r"offset_drift: .*sensor 2", timeout=60)]
            assert "sensor 2's offset has moved by +0." in line
            deadline = time.monotonic() + 15
            while True:
                status = notify.wait_for("STATUS", timeout=10)["STATUS"]
                if "OFFSET DRIFT sensor 2" in status:
                    break
                assert time.monotonic() < deadline, notify.messages[-3:]
            rc, _ = daemon.stop()
        finally:
            daemon.kill()
    assert rc == 0, daemon.text
    events = read_recordings(out).events_of("offset_drift")
    assert events and events[0].details["sensor"] == 2
    assert 0.5 < events[0].details["shift_mm"] < 1.1
    assert events[0].details["statistic"] > events[0].details["threshold"]


@pytest.mark.slow
def test_record_without_health_raises_nothing(tmp_path):
    drift = (OffsetDrift("step", 1, 2.0, 2.0),)
    with hand_emulator(rate=20, speed=10.0, drifts=drift) as emu:
        rec = record(emu.url, tmp_path, "--no-health", "--duration", "6")
        assert rec.wait(60) == 0, rec.text
    assert read_recordings(tmp_path).events_of("offset_drift") == []


def test_windows_tested_together_equal_each_window_alone():
    """step_tests (what the monitor runs, a file's windows at once) gives drift_test's
    answer for every window: shifted and clean windows, with and without the config's
    covariance, with unusable poses, and a window too short to split."""
    from loopcal.calibration.closure import Closure, step_tests
    from loopcal.calibration.implicit import predicted_volts
    from loopcal.calibration.simulate import sample_workspace

    rng = np.random.default_rng(4)
    m, B = 30, 40
    R = sample_workspace(m * B, rng, TRUTH)
    V = predicted_volts(R, TRUTH) + rng.normal(0, 0.01, (m * B, 4))
    V[m * 3 + 20 :, 2] += 0.1  # a shift of sensor 3 in the later windows
    cl = loop_closure(V, TRUTH, np.full(4, 0.01))
    shaped = [cl.error.reshape(B, m), cl.offset_pattern.reshape(B, m, 4),
              cl.information.reshape(B, m, 20), cl.usable.reshape(B, m).copy()]  # fmt: skip
    shaped[3][5, 7] = False  # an unusable pose: drift_test leaves it out
    cov = np.diag(rng.uniform(0, 0.05, 20) ** 2)
    for C in (None, cov):
        for b, got in enumerate(step_tests(*shaped, C)):
            want = drift_test(Closure(*(x[b] for x in shaped)), C, change_points=True)
            for name in ("shift_mm", "std_mm", "statistic", "margin", "chi2_rms"):
                np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-9,
                                           atol=1e-12, err_msg=f"{name} of window {b}")  # fmt: skip
            assert (got.affected, got.shape, got.poses) == (want.affected, want.shape, want.poses)
    late = step_tests(*shaped, cov)[3]  # its last 10 poses shifted
    assert (late.sensor, late.affected) == (3, 10), late
    one = [x[:1, :1] for x in shaped]
    assert step_tests(*one)[0].poses == 1
    with pytest.raises(ValueError, match="offset_pattern"):
        step_tests(shaped[0], shaped[1][:, :, :3], shaped[2], shaped[3])


def _config_off(by: dict[str, float]):
    from loopcal.calibration.parameters import INDEX

    params = np.array(TRUTH, dtype=float)
    for name, mm in by.items():
        params[INDEX[name]] += mm
    return tuple(params)


@pytest.mark.slow
@pytest.mark.parametrize(
    "config",
    [
        pytest.param(_config_off({"d04": -3.14}), id="sensor 4 replaced before the start"),
        pytest.param(tuple(nominal_config().params), id="never calibrated"),
    ],
)
def test_loops_that_never_closed_are_told_so_not_as_a_drift(config):
    scenario = HandMoves(3, params=TRUTH, pause_s=PAUSE_S)
    t_us, codes = mechanism_scans(scenario, TRUTH, 20 * 600, noise_volts=0.04, seed=3)
    rows = rows_from(t_us, codes)
    events = []
    mon = HealthMonitor(replace(nominal_config(), params=config, path="controller.toml"),
                        lambda kind, level, msg, **d: events.append((kind, msg, d)),
                        require_config=True)  # fmt: skip
    for a in range(0, len(rows), 5):
        mon.feed(rows[a : a + 5])
    kinds = [k for k, _, _ in events]
    assert kinds == ["loops_open"], events
    _, message, details = events[0]
    assert "do not close at the controller config since the recording began" in message
    assert "calibrate" in message and details["poses"] >= 6
    assert "LOOPS DO NOT CLOSE" in mon.status() and mon.state.poses > 150


def test_without_a_controller_config_health_watches_nothing_and_says_why():
    drift = (OffsetDrift("step", 2, 60.0, 2.0),)  # even a real step: nothing to hold it to
    scenario = HandMoves(3, params=TRUTH, pause_s=PAUSE_S)
    t_us, codes = mechanism_scans(scenario, TRUTH, 20 * 300, noise_volts=0.04, seed=3,
                                  drifts=drift)  # fmt: skip
    events = []
    mon = HealthMonitor(nominal_config(), lambda *a, **d: events.append(a), require_config=True)
    mon.feed(rows_from(t_us, codes))
    assert events == [] and mon.state.poses == 0 and not mon.watching
    assert "needs the robot's controller config" in mon.status()
    mon.reload(replace(nominal_config(), params=tuple(TRUTH), path="controller.toml"))
    assert mon.watching  # a reload that brings a config starts watching


def _robot_not_at_the_reference(tmp_path, *record_args: str) -> tuple[Proc, list]:
    """``loopcal record`` of an emulated robot whose geometry and offsets are not the
    reference's (as no real robot's are), nothing moving, for 120 s of device time at twenty
    times wall time; returns the recorder (stopped) and the recording's events."""
    from loopcal.calibration.parameters import NAMES

    truth = truth_for(11)
    every = ",".join(f"{n}={float(truth[i])!r}" for i, n in enumerate(NAMES))
    sim = Proc(["simulate", "--seed", "11", "--speed", "20", "--pause", "0.8,1.5",
                "--twist-every", "0", "--noise-mv", "40", "--truth", every,
                "--wait-for-client"])  # fmt: skip
    from tests.support.processes import listening_url

    try:
        proc = record(listening_url(sim), tmp_path / "rec", "--read-period", "0.05",
                      "--duration", "6", *record_args)  # fmt: skip
        assert proc.wait(90) == 0, proc.text
    finally:
        sim.kill()
    return proc, read_recordings(tmp_path / "rec").events


@pytest.mark.slow
def test_a_recorder_without_a_controller_config_raises_no_alarm(tmp_path):
    proc, events = _robot_not_at_the_reference(tmp_path)
    assert "loop-closure health watches nothing: it needs the robot's controller config" \
        in proc.text  # fmt: skip
    kinds = {e.kind for e in events}
    assert not kinds & {"offset_drift", "loops_open"}, kinds


@pytest.mark.slow
def test_a_recorder_whose_config_never_fitted_says_so_not_a_drift(tmp_path):
    never = tmp_path / "controller.toml"
    assert Proc(["init-config", str(never)]).wait(60) == 0  # the reference geometry
    proc, events = _robot_not_at_the_reference(tmp_path, "--controller-config", str(never))
    kinds = [e.kind for e in events if e.kind in ("offset_drift", "loops_open")]
    assert kinds == ["loops_open"], [e.message for e in events]
    assert "the loops do not close at the controller config since the recording began" \
        in proc.text  # fmt: skip


def test_a_feed_searches_its_new_scans_not_every_scan_since_the_last_pose():
    """While the plate moves (20 s without a still pose), the monitor keeps two windows and
    a gap's margin of scans for the next search (24 at 20 Hz), not every scan since the
    last pose (up to 15 s): a feed's work follows its new scans."""
    n = 20 * 20
    sweep = (np.arange(n) * 20) % 1500  # 0.1 V a scan: never still
    rows = rows_from(np.arange(n) * 50_000, 1000 + sweep[:, None] + np.arange(4) * 300)
    mon = HealthMonitor(replace(nominal_config(), params=tuple(TRUTH)), lambda *a, **d: None)
    kept = []
    for a in range(0, n, 20):
        mon.feed(rows[a : a + 20])
        kept.append(len(mon._buf))
    assert mon.state.poses == 0 and max(kept) == 2 * 10 + 5 - 1, kept


@pytest.mark.slow
def test_poses_fed_a_second_at_a_time_are_those_of_one_search_over_the_session():
    """Across gaps and a restart, the poses the monitor tests, fed a second of scans at a
    time and keeping only what a later pose can need, are those one search over the whole
    session completes."""
    from loopcal.daemon.live.health import MIN_AFFECTED
    from loopcal.daemon.worker.recorded_poses import completed_poses

    scenario = HandMoves(3, params=TRUTH, pause_s=PAUSE_S)
    t_us, codes = mechanism_scans(scenario, TRUTH, 20 * 900, noise_volts=0.04, seed=3)
    rows = rows_from(t_us, codes)
    rng = np.random.default_rng(3)
    keep = np.ones(len(rows), dtype=bool)
    for g in rng.integers(100, len(rows) - 100, 8):  # eight gaps of up to 30 scans
        keep[g : g + rng.integers(1, 30)] = False
    rows = rows[keep].copy()
    jump = np.diff(rows["counter64"].astype(np.int64))
    rows["missed"][1:] = np.where(jump > 1, jump - 1, 0)
    r = int(0.6 * len(rows))  # the module restarts there
    rows["epoch"][r:] += 1
    rows["restarted"][r] = True
    tested = []
    mon = HealthMonitor(replace(nominal_config(), params=tuple(TRUTH)), lambda *a, **d: None,
                        on_test=lambda stamp, _: tested.append(stamp))  # fmt: skip
    for a in range(0, len(rows), 20):
        mon.feed(rows[a : a + 20])
    P, done, _ = completed_poses(rows)
    assert mon.state.poses == len(done) > 250
    assert tested == P.stamp_ns[done][MIN_AFFECTED - 1 :].tolist()


@pytest.mark.slow
def test_loops_open_at_a_calibrated_config_are_a_change_since_its_calibration():
    """A sensor replaced before the start at a config loopcal calibrated: said as a change
    since that calibration, with the sensors that may have moved, not as a config that
    does not describe the robot."""
    scenario = HandMoves(3, params=TRUTH, pause_s=PAUSE_S)
    t_us, codes = mechanism_scans(scenario, TRUTH, 20 * 300, noise_volts=0.04, seed=3)
    rows = rows_from(t_us, codes)
    events = []
    config = replace(nominal_config(), params=_config_off({"d04": -0.8}), path="controller.toml",
                     provenance={"written_utc": "2026-12-01T08:00:00Z", "method": "ml",
                                 "std": {n: 0.01 for n in ("d01", "d02", "d03", "d04")}})
    mon = HealthMonitor(config, lambda kind, level, msg, **d: events.append((kind, msg, d)),
                        require_config=True)
    for a in range(0, len(rows), 5):
        mon.feed(rows[a : a + 5])
    assert [k for k, _, _ in events] == ["loops_open"], events
    _, message, details = events[0]
    assert "changed since its calibration (2026-12-01T08:00:00Z)" in message
    assert "does not describe this robot" not in message
    assert details["calibrated_utc"] == "2026-12-01T08:00:00Z"
    assert 4 in [c["sensor"] for c in details["candidates"]]
    assert "changed since its calibration" in mon.status()


@pytest.mark.slow
def test_a_drift_the_poses_cannot_attribute_is_said_with_its_candidates():
    """A task loop of two waypoints cannot tell sensor 3 from sensor 4: sensor 4's step is
    said within half a minute as one of them, with the move that tells them apart, kept in
    the status line and the metrics; no sensor is named that the poses cannot tell."""
    from loopcal.simulator.task import TaskLoop

    truth = truth_for(1)
    t_us, codes = mechanism_scans(TaskLoop(1, waypoints=2), truth, 20 * 240, seed=1,
                                  drifts=(OffsetDrift("step", 4, 60.0, -0.6),))
    rows = rows_from(t_us, codes)
    events, clock = [], [0.0]
    mon = HealthMonitor(replace(nominal_config(), params=tuple(truth)),
                        lambda kind, level, msg, **d: events.append((clock[0], kind, msg, d)))
    for a in range(0, len(rows), 20):
        clock[0] = t_us[min(a + 19, len(rows) - 1)] / 1e6
        mon.feed(rows[a : a + 20])
    said = [e for e in events if e[1] == "offset_drift_unattributed"]
    assert said and said[0][0] - 60.0 <= 30.0, events
    sensors = [c["sensor"] for c in said[0][3]["candidates"]]
    assert 3 in sensors and 4 in sensors and said[0][3]["advice"], said
    assert not [e for e in events if e[1] == "offset_drift" and e[3]["sensor"] != 4]
    assert "LOOPS OPEN" in mon.status()
    metrics = {m.name: m for m in mon.metrics()}
    assert metrics["loopcal_loops_open"].samples[0].value == 1.0
