"""Live guidance: ``loopcal record --until-enough`` stops by itself on an emulated session,
and its last prediction is what ``loopcal calibrate`` then reports."""

from __future__ import annotations

import json

import numpy as np
import pytest

from loopcal.calibration.parameters import INDEX, NAMES, PAPER7
from loopcal.daemon.config.controller import nominal_config
from loopcal.daemon.live.guidance import COVERAGE_SCANS, Guidance
from loopcal.daemon.recording import read_recordings
from loopcal.daemon.worker import coverage as C
from loopcal.daemon.worker.job import run_worker
from loopcal.daemon.worker.scan_poses import scans_for_fit
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.scenarios import HandMoves, Static
from tests.support.processes import Proc, calibrate_json, fresh_config, listening_url, record
from tests.support.rows import rows_from
from tests.support.sessions import PAUSE_S, hand_rows, trim, truth_for

pytestmark = pytest.mark.timeout(180)


@pytest.mark.slow
def test_guidance_predicts_what_the_worker_reports_and_stops_when_enough():
    truth = truth_for(5)
    t_us, codes = mechanism_scans(HandMoves(5, params=truth, pause_s=PAUSE_S), truth, 20 * 300,
                                  noise_volts=0.04, seed=5)  # fmt: skip
    rows = rows_from(t_us, codes)
    updates = []
    enough = []
    g = Guidance(nominal_config(), PAPER7, target_mm=0.1, on_update=updates.append,
                 on_enough=enough.append, period_s=0)  # fmt: skip
    for a in range(0, len(rows), 20):
        g.feed(rows[a : a + 20])
        if g.done:
            break
    assert g.done and len(enough) == 1 and enough[0] is updates[-1]
    last = updates[-1]
    assert last.enough and all(last.gates.values()) and last.poses >= 30
    assert all(last.std[n] <= 0.1 for n in ("d01", "d02", "d03", "d04"))
    # early on, before the worker can run, the information predicts the precision
    early = [u for u in updates if 10 <= u.poses < 30]
    assert early and all(np.isfinite(list(u.std.values())).all() for u in early[-3:])
    assert not any(u.enough for u in updates[:-1])
    # the prediction is the worker's own result on the same scans
    seen = rows[: last.scans]
    result = run_worker(seen, nominal_config(), PAPER7)
    assert {n: pytest.approx(s) for n, s in result.std.items()} == last.std
    text = "\n".join(last.render())
    assert "ENOUGH" in text and "sensor 4" in text and "d03" in text
    doc = json.loads(json.dumps(last.as_json()))
    assert doc["enough"] is True
    # how far the plate was twisted each way, as the worker's advice judges it
    usable = scans_for_fit(seen).volts
    step = max(1, -(-len(usable) // COVERAGE_SCANS))
    twist = C.twist_coverage(usable[::step], np.array(nominal_config().params))
    assert last.twist_deg == pytest.approx(twist.tolist()) and min(twist) > 0
    assert doc["twist_deg"] == {"clockwise": round(twist[0], 1),
                                "counter_clockwise": round(twist[1], 1)}  # fmt: skip
    assert f"clockwise {twist[0]:.1f} deg, counter-clockwise {twist[1]:.1f} deg" in text


def test_a_plate_left_still_is_asked_to_move_and_a_moving_one_where_to():
    truth = truth_for(3)
    updates = []
    g = Guidance(nominal_config(), PAPER7, target_mm=0.1, on_update=updates.append,
                 period_s=0)  # fmt: skip
    t_us, codes = mechanism_scans(Static((0.0, 12.0, 0.0)), truth, 20 * 12, noise_volts=0.04,
                                  seed=3)  # fmt: skip
    still = rows_from(t_us, codes)
    for a in range(0, len(still), 20):
        g.feed(still[a : a + 20])
    # not before ten seconds at rest; then told to move, tilting and twisting
    assert all("move the plate:" not in u.instruction for u in updates[:9])
    told = "move the plate: tilt and twist it by hand through new positions"
    assert updates[-1].instruction == told
    assert updates[-1].twist_deg == pytest.approx([0.0, 0.0], abs=0.5)
    moving = Guidance(nominal_config(), PAPER7, target_mm=0.1, on_update=updates.append,
                      period_s=0)  # fmt: skip
    moving.feed(hand_rows(20 * 20, seed=3))
    assert "move the plate:" not in updates[-1].instruction
    assert updates[-1].instruction.startswith(("tilt the plate further", "twist the plate"))


@pytest.mark.slow
def test_until_enough_stops_by_itself_and_calibrate_agrees(tmp_path):
    seed = 7
    truth = truth_for(seed)
    every = ",".join(f"{n}={float(truth[i])!r}" for i, n in enumerate(NAMES))
    config = fresh_config(tmp_path / "controller.toml")
    sim = Proc(["simulate", "--seed", str(seed), "--speed", "10", "--wait-for-client",
                "--pause", f"{PAUSE_S[0]},{PAUSE_S[1]}", "--twist-every", "0",
                "--truth", every])  # fmt: skip
    try:
        rec = record(listening_url(sim), tmp_path / "rec", "--controller-config", str(config),
                     "--until-enough", "--json", "--read-period", "0.05")  # fmt: skip
        rc = rec.wait(120)
    finally:
        sim.kill()
    assert rc == 0, rec.text
    lines = [json.loads(line) for line in rec.lines if line.startswith("{")]
    *updates, summary = lines  # the guidance updates, then record's summary (JSON lines)
    assert summary["summary"] is True and summary["enough"] is True
    assert summary["exit_status"] == 0 and summary["scans_written"] == len(
        read_recordings(tmp_path / "rec").scans)  # fmt: skip
    assert not any("summary" in u for u in updates)
    assert len(updates) >= 3 and updates[-1]["enough"] is True
    assert not any(u["enough"] for u in updates[:-1])
    assert "stopped (enough to calibrate)" in rec.text
    out = read_recordings(tmp_path / "rec")
    assert all(f.complete for f in out.files)
    assert out.events_of("guidance")[0].details["enough"] is True
    predicted = updates[-1]["std"]
    # on the scans the guidance judged, calibrate reports what it predicted; the whole
    # recording holds the scans recorded while it stopped too (every scan counts: at ten
    # times, a second's lag on a loaded machine is ten seconds of motion), no less precise
    seen = trim(tmp_path / "rec", tmp_path / "seen", 0, updates[-1]["scans"])
    for where, rel in ((seen, 0.02), (tmp_path / "rec", None)):
        code, doc, err = calibrate_json(where, "--controller-config", config)
        assert code == 0 and doc["accepted"], err
        for name, p in doc["parameters"].items():
            if rel is not None:
                assert p["std"] == pytest.approx(predicted[name], rel=rel), name
            else:
                assert p["std"] <= predicted[name] * 1.02, name
            assert abs(p["value"] - truth[INDEX[name]]) <= 3 * p["std"], name


@pytest.mark.slow
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--target-mm", "0.2"], "--target-mm goes with --until-enough"),
        (["--until-enough", "--target-mm", "0"], "a target must be more than 0 and at most 10 mm"),
        (["--until-enough", "--controller-config", "/nonexistent.toml"], "nonexistent.toml"),
    ],
)
def test_bad_guidance_options_are_named(tmp_path, args, message):
    p = record("modbus-tcp://127.0.0.1:1", tmp_path, *args)
    assert p.wait(30) == 2
    assert message in p.text
