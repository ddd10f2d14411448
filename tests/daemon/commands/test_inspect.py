"""``loopcal info`` and ``loopcal check`` on real recording files, run by cli.main in this
process; check's report of what the daemon's upkeep would propose, from a robot at work (a
task loop)."""

from __future__ import annotations

import json
import re
import shutil
import time
from datetime import datetime

import numpy as np
import pytest

from loopcal.calibration.parameters import INDEX
from loopcal.daemon import recording as rec
from loopcal.daemon.config.controller import load_controller_config, write_initial_config
from loopcal.daemon.events import Event, Level
from loopcal.daemon.live.upkeep import Upkeep
from loopcal.daemon.recorder.settings import DEFAULTS
from loopcal.daemon.worker.proposal import proposal_path
from loopcal.daemon.worker.recorded_poses import poses_of_scans
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.scenarios import HandMoves
from loopcal.simulator.task import TaskLoop
from tests.support.emulator import hand_emulator
from tests.support.mutations import tear_chunk
from tests.support.processes import loopcal_main, record
from tests.support.recordings import write_directory, write_rows
from tests.support.rows import T0, make_rows, rows_from
from tests.support.sessions import PAUSE_S, truth_for, write_session

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def _write(path, rows, events=()):
    write_rows(
        path,
        rows,
        events=events,
        metadata=rec.metadata_records(
            device={"model": "LDQ412", "serial": "12648430"},
            controller={
                "path": "/etc/loopcal/controller/controller.toml",
                "sha256": "ab" * 32,
                "provenance": json.dumps(
                    {"written_utc": "2026-11-20T10:00:00+00:00", "method": "ml"}
                ),
            },  # fmt: skip
            command="pytest",
        ),
        params=np.array(truth_for(1)),
        fsync=False,
    )


def test_info_counts_scans_gaps_restarts_events_and_damage(tmp_path):
    a = make_rows(1000, epoch=0)
    a["counter64"][500:] += 3  # three scans never received
    a["missed"][500] = 3
    b = make_rows(600, epoch=1, t0=T0 + 60 * 10**9)  # the module restarted
    b["restarted"][0] = True
    evs = [
        Event(int(a["stamp_ns"][500]), "gap", Level.WARNING, "3 missed", {"missed": 3}),
        Event(int(b["stamp_ns"][0]), "restart", Level.WARNING, "restart", {"epoch": 1}),
    ]
    d = tmp_path / "rec"
    d.mkdir()
    fa, fb = d / rec.recording_name(T0), d / rec.recording_name(T0 + 60 * 10**9)
    _write(fa, a, evs)
    _write(fb, b, evs)
    shutil.copy(fa, d / rec.recording_name(T0 + 10**6))  # a copy: counted once
    proc = loopcal_main("info", d, "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["scans"] == 1600 and len(doc["files"]) == 3
    assert doc["missed"] == 3 and doc["gaps"] == 1
    assert doc["restarts"] == 1 and doc["power_ons"] == 2
    assert doc["powered_on_utc"] is None  # the first scan has no restart flag: powered on before
    assert doc["events"] == {"gap": 1, "restart": 1}
    assert doc["start_utc"] == "2026-11-18T11:06:40.000Z"  # T0, as every command spells it
    assert doc["scan_rate_hz"] == pytest.approx(20.0)
    assert doc["poses"] == 0 and doc["warnings"] == []  # every scan a new pose: none still
    [cfg] = doc["controller_configs"]
    assert cfg["calibrated_utc"].startswith("2026-11-20") and cfg["method"] == "ml"
    # damage a file: info says what was lost, by name
    tear_chunk(fb, 8, head=40)
    proc = loopcal_main("info", d)
    assert proc.returncode == 0
    assert "scan(s) missing" in proc.stdout and fb.name in proc.stdout
    assert "restarts:   1 (power-ons seen: 2)" in proc.stdout and "gap" in proc.stdout
    assert "powered on: before the first scan" in proc.stdout
    bad = loopcal_main("info", tmp_path / "nothing-here")
    assert bad.returncode == 2 and "no such file" in bad.stderr


@pytest.mark.parametrize("power_cycle", [False, True], ids=["never-restarted", "power-cycled"])
def test_info_names_the_power_on_and_counts_restarts_after_it(tmp_path, power_cycle):
    """A real recording through ``loopcal record``: the module's first scan after power-on
    carries the restart flag; info names that the power-on and counts only the restarts
    after it, as many as the emulated module really had (its power cycles)."""
    out = tmp_path / "rec"
    with hand_emulator(speed=5.0) as emu:  # switched on by the recorder's first request
        proc = record(emu.url, out)
        try:
            proc.wait_for(r"connect: LDQ412", 30)
            time.sleep(1.0)
            if power_cycle:
                emu.faults.restart()
                proc.wait_for(r"restart: module restarted", 30)
                time.sleep(1.0)
            assert proc.stop(30)[0] == 0, proc.text
        finally:
            proc.kill()
        boots = {s.boot for s in emu.truth}
    assert len(boots) == (2 if power_cycle else 1)
    scans = rec.read_recordings(out).scans
    assert scans["restarted"][0] and scans["counter64"][0] == 0  # recorded from power-on
    doc = json.loads(loopcal_main("info", out, "--json").stdout)
    assert doc["restarts"] == len(boots) - 1 and doc["power_ons"] == len(boots)
    assert doc["powered_on_utc"] == doc["start_utc"] is not None
    text = loopcal_main("info", out).stdout
    assert f"powered on: {doc['start_utc']} " in text  # one spelling, text and JSON
    assert f"restarts:   {len(boots) - 1} since (power-ons seen: {len(boots)})" in text


@pytest.fixture(scope="module")
def drifting(tmp_path_factory):
    """Eight minutes of a hand-moved session whose sensor 3 offset steps by +0.5 mm at
    240 s, and a controller config with the mechanism's true values."""
    d = tmp_path_factory.mktemp("drift")
    truth = truth_for(5)
    write_session(d / "rec", HandMoves(5, params=truth, pause_s=PAUSE_S), truth, 480, seed=5,
                  hours_per_file=2 / 60, drifts=(OffsetDrift("step", 3, 240.0, 0.5),))  # fmt: skip
    config = write_initial_config(d / "controller.toml", params=truth)
    return d / "rec", config


def test_check_names_the_sensor_when_and_how_much(drifting, tmp_path):
    rec_dir, config = drifting
    png = tmp_path / "check.png"
    proc = loopcal_main("check", rec_dir, "--controller-config", config, "--json", "--plot", png)
    assert proc.returncode == 1, proc.stderr
    doc = json.loads(proc.stdout)
    assert not doc["loops_close"] and len(doc["recordings"]) == 4
    [change] = doc["changes"]
    assert change["sensor"] == 3 and change["shape"] in ("step", "creep")
    assert abs(change["shift_mm"] - 0.5) < 4 * change["std_mm"] + 0.05
    start = datetime.fromisoformat(change["start_utc"]).timestamp()
    assert abs(start - (T0 / 1e9 + 240)) < 30  # the first still pose it shifted
    assert abs(change["start_offset_s"] - 240) < 30
    assert datetime.fromisoformat(change["detected_utc"]).timestamp() > start
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000
    human = loopcal_main("check", rec_dir, "--controller-config", config)
    assert human.returncode == 1 and "sensor 3: offset moved by +0." in human.stdout
    info = json.loads(loopcal_main("info", rec_dir, "--json").stdout)
    assert info["scans"] == 480 * 20 and info["poses"] >= doc["poses"] > 100


def test_check_is_quiet_where_the_loops_close(drifting, tmp_path):
    rec_dir, config = drifting
    first = sorted(rec_dir.glob("*.mcap"))[:2]  # the four minutes before the step
    proc = loopcal_main("check", *first, "--controller-config", config, "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["loops_close"] and doc["changes"] == [] and doc["poses"] > 60
    bad = loopcal_main("check", *first, "--controller-config", tmp_path / "none.toml")
    assert bad.returncode == 2 and "no such file" in bad.stderr


def test_check_tells_loops_that_never_closed_from_a_drift(drifting, tmp_path):
    """A config never calibrated (the reference geometry: every offset and the geometry
    off) is no sensor moving: check says the loops never closed, once, names no sensor
    as moved, and counts the still poses as info does."""
    rec_dir, _ = drifting
    first = sorted(rec_dir.glob("*.mcap"))[:2]
    never = write_initial_config(tmp_path / "never.toml")  # the reference geometry
    proc = loopcal_main("check", *first, "--controller-config", never, "--json")
    assert proc.returncode == 1, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["changes"] == [] and not doc["loops_close"], doc["changes"]
    assert doc["loops_open"]["poses"] >= 6 and "calibrate" in doc["loops_open"]["message"]
    info = json.loads(loopcal_main("info", *first, "--json").stdout)
    # both count as one search over the files' scans at once would (a pose across the file
    # boundary is one pose), the pose they end in included
    whole = poses_of_scans(rec.read_recordings(first).scans)
    assert doc["poses"] == info["poses"] == len(whole)
    text = loopcal_main("check", *first, "--controller-config", never).stdout
    assert "The loops do not close at this config since the recordings began" in text
    assert "offset moved" not in text


def test_check_says_the_shape_and_whether_the_loops_closed_again(drifting):
    rec_dir, config = drifting
    text = loopcal_main("check", rec_dir, "--controller-config", config).stdout
    line = next(x for x in text.splitlines() if x.startswith("sensor 3: offset moved"))
    assert ", a step)" in line or ", a creep, still moving)" in line, line
    assert "the loops have not closed again" in line or "closed again at" in line, line


def _robot_at_work(d, seed, seconds, drifts=()):
    """A task loop's scans as a recorder leaves them (a file a minute) in ``d / "rec"``,
    and a controller config at the mechanism's truth; (truth, rows, directory, config)."""
    truth = truth_for(seed)
    t_us, codes = mechanism_scans(TaskLoop(seed), truth, int(seconds * 20), seed=seed,
                                  drifts=tuple(drifts))  # fmt: skip
    rows = rows_from(t_us, codes)
    write_directory(d / "rec", rows, scans_per_file=1200)
    return truth, rows, d / "rec", write_initial_config(d / "controller.toml", params=truth)


@pytest.fixture(scope="module")
def swapped(tmp_path_factory):
    """Five minutes of a robot at work whose sensor 3 offset steps by +0.8 mm at 120 s."""
    return _robot_at_work(tmp_path_factory.mktemp("swapped"), 1, 300,
                          [OffsetDrift("step", 3, 120.0, 0.8)])  # fmt: skip


def test_check_reports_what_upkeep_would_propose(swapped):
    truth, rows, rec_dir, config = swapped
    proc = loopcal_main("check", rec_dir, "--controller-config", config, "--json")
    assert proc.returncode == 1, proc.stderr
    doc = json.loads(proc.stdout)
    [p] = doc["proposals"]
    assert p["names"] == ["d03"] and p["scans"] >= 300 and all(p["gates"].values())
    want = truth[INDEX["d03"]] + 0.8
    assert abs(p["values"]["d03"] - want) <= 0.05, (p, want)
    assert abs(p["shift_mm"]["d03"] - 0.8) <= 0.05 and 0 < p["scans_std"]["d03"] <= 0.05
    # a config loopcal never calibrated: its offsets held at 0.05 mm each carry into d03
    assert p["std"]["d03"] > 0.05 > p["scans_std"]["d03"]
    began = T0 / 1e9 + 120
    assert abs(datetime.fromisoformat(p["since_utc"]).timestamp() - began) <= 15
    assert abs(p["since_offset_s"] - 120) <= 15
    since, until = (datetime.fromisoformat(p[k]).timestamp()
                    for k in ("window_since_utc", "window_until_utc"))  # fmt: skip
    assert began - 15 <= since < until <= began + 240
    assert doc["pending_proposal"] is None
    text = loopcal_main("check", rec_dir, "--controller-config", config).stdout
    line = next(x for x in text.splitlines() if x.startswith("upkeep would propose"))
    shift = f"{p['shift_mm']['d03']:+.3f}"
    assert f"d03 = {p['values']['d03']:.4f} mm ({shift} +- " in line, line
    assert p["since_utc"] in line, line
    assert f"from {p['window_since_utc']} to {p['window_until_utc']}" in line, line


def test_check_proposes_nothing_for_a_robot_unchanged(tmp_path):
    _, _, rec_dir, config = _robot_at_work(tmp_path, 2, 300)
    proc = loopcal_main("check", rec_dir, "--controller-config", config, "--json")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["proposals"] == [] and doc["loops_close"] and doc["pending_proposal"] is None
    text = loopcal_main("check", rec_dir, "--controller-config", config).stdout
    assert "upkeep would propose no recalibration." in text and "pending" not in text


def test_check_names_the_proposal_pending_beside_the_config(swapped, tmp_path):
    """The daemon's own proposal (its upkeep in propose mode over the same scans) is named
    with its values and when it was proposed; one edited by hand, with why it cannot be
    taken."""
    truth, rows, rec_dir, _ = swapped
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    up = Upkeep(load_controller_config(config), lambda *a, **k: None, mode="propose",
                target_mm=DEFAULTS["upkeep_target_mm"],
                threshold_mm=DEFAULTS["upkeep_threshold_mm"],
                min_interval_s=DEFAULTS["upkeep_min_interval_s"], threaded=False)  # fmt: skip
    up.feed(rows)
    assert up.state.pending is not None
    doc = json.loads(loopcal_main("check", rec_dir, "--controller-config", config, "--json").stdout)
    pending = doc["pending_proposal"]
    assert pending["error"] is None and pending["path"] == str(proposal_path(config))
    assert pending["values"] == up.state.pending.values and pending["since_utc"]
    [p] = doc["proposals"]  # the reference is the config alone: the same change found
    assert p["values"]["d03"] == pytest.approx(pending["values"]["d03"], abs=1e-4)
    text = loopcal_main("check", rec_dir, "--controller-config", config).stdout
    assert (f"pending proposal {pending['path']} since {pending['since_utc']}: "
            f"d03 = {pending['values']['d03']:.4f} mm") in text  # fmt: skip
    path = proposal_path(config)
    edited = f"d03 = {pending['values']['d03'] + 0.1!r}"  # [parameters] edited by hand
    path.write_text(re.sub(r"^d03 = .*$", edited, path.read_text(), count=1, flags=re.M))
    doc = json.loads(loopcal_main("check", rec_dir, "--controller-config", config, "--json").stdout)
    damaged = doc["pending_proposal"]
    assert "edited" in damaged["error"] and damaged["values"] is None
    text = loopcal_main("check", rec_dir, "--controller-config", config).stdout
    assert "pending proposal" in text and "cannot be taken" in text and "edited" in text


def test_check_takes_the_daemons_upkeep_settings_or_the_options(swapped):
    """A threshold above the shift: nothing proposed; out of the daemon's bounds: bad input."""
    _, _, rec_dir, config = swapped
    proc = loopcal_main("check", rec_dir, "--controller-config", config, "--json",
                   "--upkeep-threshold-mm", "5")  # fmt: skip
    assert json.loads(proc.stdout)["proposals"] == []
    bad = loopcal_main("check", rec_dir, "--controller-config", config, "--upkeep-target-mm", "0")
    assert bad.returncode == 2 and "--upkeep-target-mm 0" in bad.stderr


def test_check_names_both_sensors_where_the_poses_cannot_tell_which(tmp_path):
    """A two-waypoint task loop cannot tell sensor 3 from sensor 4: check names both, and
    the upkeep it runs would propose nothing (it names no sensor it cannot tell)."""
    truth = truth_for(1)
    t_us, codes = mechanism_scans(TaskLoop(1, waypoints=2), truth, 300 * 20, seed=1,
                                  drifts=(OffsetDrift("step", 4, 90.0, -0.6),))
    write_directory(tmp_path / "rec", rows_from(t_us, codes), scans_per_file=1200)
    config = write_initial_config(tmp_path / "controller.toml", params=truth)
    proc = loopcal_main("check", tmp_path / "rec", "--controller-config", config, "--json")
    assert proc.returncode == 1, proc.stderr
    doc = json.loads(proc.stdout)
    [change] = doc["changes"]
    assert change["sensor"] is None and {3, 4} <= set(change["candidates"]), change
    assert doc["proposals"] == []
    human = loopcal_main("check", tmp_path / "rec", "--controller-config", config).stdout
    assert "(the poses could not tell which)" in human and "Verdict: 1 change found" in human
