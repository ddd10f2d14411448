"""``loopcal calibrate`` and ``loopcal replay`` end to end: technician sessions (the
simulator's scans; through a real transport and recorder in the replay round trips),
degenerate recordings the gates must refuse, killing the worker
while it writes, replay round trips, and bad input."""

from __future__ import annotations

import os
import re
import signal
import time
from datetime import UTC, datetime

import numpy as np
import pytest
import tomlkit

from loopcal.calibration.parameters import INDEX, NAMES, NOMINAL
from loopcal.daemon.config import durable
from loopcal.daemon.config.controller import load_controller_config
from loopcal.daemon.recording import read_recordings
from loopcal.daemon.worker.writeback import STEPS
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.scenarios import HandMoves, Static, Sweep
from tests.support.processes import Proc, calibrate_json, fresh_config, loopcal, loopcal_main
from tests.support.recordings import write_rows
from tests.support.replay import finish, replay_and_record
from tests.support.sessions import PAUSE_S, Session, trim, truth_for, write_session

pytestmark = pytest.mark.timeout(300)

SEEDS = [11, 12, 13]


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """Three technician sessions at the paper's noise, a little longer than two minutes
    (the tests use exactly two: the same scans every run), written straight from the
    simulator: the emulator's scans, as a recorder keeps them. That they come through the
    wire and the recorder unchanged is test_replay_round_trip_is_exact_and_calibrates's to
    show (and tests/daemon/recorder's), not these statistics'."""
    root, out = tmp_path_factory.mktemp("sessions"), []
    for seed in SEEDS:
        truth, d = truth_for(seed), root / f"session-{seed}"
        write_session(d, HandMoves(seed, params=truth, pause_s=PAUSE_S), truth, 2.7 * 60,
                      seed=seed)  # fmt: skip
        out.append(Session(d, truth, seed))
    return out


@pytest.fixture(scope="module")
def offline(tmp_path_factory):
    """A 2-minute session written straight from the simulator (for the fast tests)."""
    d = tmp_path_factory.mktemp("offline")
    truth = truth_for(4)
    write_session(d, HandMoves(4, params=truth, pause_s=PAUSE_S), truth, 120, seed=4)
    return d, truth


@pytest.mark.slow
def test_sessions_calibrate_within_three_standard_deviations(sessions, tmp_path, capsys):
    errors = []
    for s in sessions:
        config = fresh_config(tmp_path / f"controller-{s.seed}.toml")
        # exactly two minutes, scans 600..2999: the same scans every run
        two = trim(s.directory, tmp_path / f"two-{s.seed}", 600, 3000)
        rc, doc, err = calibrate_json(two, "--controller-config", config)
        assert rc == 0 and doc["accepted"], (err, doc.get("gates"))
        assert doc["poses"]["found"] >= 40 and doc["poses"]["scans"] == 2400
        for name, p in doc["parameters"].items():
            e = p["value"] - s.truth[INDEX[name]]
            errors.append((s.seed, name, e, p["std"]))
            assert abs(e) <= 3 * p["std"], (s.seed, name, e, p["std"])
    with capsys.disabled():
        print("\n  session errors (mm): " + ", ".join(f"{n} {e:+.3f}" for _, n, e, _ in errors))
    z = np.array([e / sd for *_, e, sd in errors])
    assert np.sqrt(np.mean(z**2)) < 2.0  # the standard deviations are honest
    # 75 s of the same sessions (scans 600..2099): still poses were too few for a fit;
    # every scan counts, and they are accepted, the errors within their bounds
    for s in sessions:
        config = fresh_config(tmp_path / f"controller-75-{s.seed}.toml")
        short = trim(s.directory, tmp_path / f"short-{s.seed}", 600, 2100)
        rc, doc, err = calibrate_json(short, "--controller-config", config)
        assert rc == 0 and doc["accepted"], (err, doc.get("gates"))
        assert doc["poses"]["scans"] == 1500
        for name, p in doc["parameters"].items():
            assert abs(p["value"] - s.truth[INDEX[name]]) <= 3 * p["std"], (s.seed, name)
        rc, doc, _ = calibrate_json(short, "--controller-config", config, "--method", "paper")
        assert rc == 1 and not doc["accepted"]


@pytest.mark.slow
def test_write_keeps_comments_and_the_previous_version(offline, tmp_path):
    rec_dir, truth = offline
    config = fresh_config(tmp_path / "controller.toml")
    config.chmod(0o644)  # a controller reading it as another user
    before = config.read_text()
    old_umask = os.umask(0o027)  # as the systemd units' UMask: must not narrow the mode
    try:
        proc = loopcal_main("calibrate", rec_dir, "--controller-config", config, "--write")
    finally:
        os.umask(old_umask)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert config.stat().st_mode & 0o777 == 0o644
    assert "Wrote 10 value(s)" in proc.stdout
    prev = list(tmp_path.glob("controller.toml.*.prev"))
    assert len(prev) == 1 and prev[0].read_text() == before
    new = load_controller_config(config)
    for name in ("d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"):
        assert abs(new.params[INDEX[name]] - truth[INDEX[name]]) < 0.5
    assert new.params[INDEX["A4x"]] == -new.params[INDEX["A1x"]]  # ties written too
    assert new.params[INDEX["k3"]] == NOMINAL[INDEX["k3"]]
    kept = [line for line in before.splitlines() if line.startswith("#")]
    after = config.read_text().splitlines()
    assert all(line in after for line in kept)
    prov = new.provenance
    assert (
        prov["recordings"]
        and prov["poses_used"] >= 30
        and set(prov["std"]) == {"d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"}
    )
    assert prov["previous"]["d01"] == 97.4


@pytest.mark.slow
@pytest.mark.parametrize(
    ("case", "method", "gate", "words"),
    [
        ("barely moved", "ml", "poses", "barely moved"),
        ("barely moved", "paper", "poses", "barely moved"),
        ("sensor 2 stuck", "ml", "poses", "sensor 2"),
        ("sensor 2 stuck", "paper", "poses", "sensor 2"),
        # the paper's method needs still poses; ml takes every scan, and one circle of the
        # plate, repeated, does not tell the base points apart
        ("never still", "paper", "poses", "still poses"),
        ("never still", "ml", "precision", "known only to"),
        # the plate swung a few degrees about one tilt: told which way to tilt instead
        ("bunched", "ml", "condition", "tilt the plate further toward sensor"),
    ],
)
def test_degenerate_recordings_are_refused(tmp_path, case, method, gate, words):
    truth = truth_for(3)
    if case == "bunched":
        write_session(tmp_path / "rec", Sweep(period_s=10.0, tilt_deg=5.0, swivel_deg=5.0),
                      truth, 120, seed=3)  # fmt: skip
    elif case == "barely moved":
        write_session(tmp_path / "rec", Static((0.0, 3.0, 0.0)), truth, 240, seed=3)
    elif case == "sensor 2 stuck":

        def stuck(codes):
            codes[:, 1] = 2500

        write_session(
            tmp_path / "rec",
            HandMoves(3, params=truth, pause_s=PAUSE_S),
            truth,
            120,
            seed=3,
            edit=stuck,
        )
    else:
        write_session(tmp_path / "rec", Sweep(period_s=10.0), truth, 120, seed=3)
    config = fresh_config(tmp_path / "controller.toml")
    before = config.read_bytes()
    proc = loopcal_main("calibrate", tmp_path / "rec", "--controller-config", config, "--write",
                   "--method", method)  # fmt: skip
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert f"[FAIL] {gate}" in proc.stdout and words in proc.stdout
    assert "REFUSED" in proc.stdout and "do:" in proc.stdout
    assert config.read_bytes() == before and not list(tmp_path.glob("*.prev"))
    rc, doc, _ = calibrate_json(tmp_path / "rec", "--controller-config", config,
                                "--method", method)  # fmt: skip
    assert rc == 1 and not doc["accepted"]
    failed = [g for g in doc["gates"] if not g["passed"]]
    assert failed[0]["name"] == gate and failed[0]["advice"]
    assert words in failed[0]["reason"] + failed[0]["advice"]


@pytest.mark.slow
def test_a_loose_gain_fails_validation_not_silently(offline, tmp_path):
    """A wrong gain in the config (S3 off by 5 %): the loops cannot close; refused."""
    rec_dir, _ = offline
    config = fresh_config(tmp_path / "controller.toml")
    doc = tomlkit.parse(config.read_text())
    doc["parameters"]["S3"] = 3.75 * 1.05
    config.write_text(tomlkit.dumps(doc))
    rc, out, _ = calibrate_json(rec_dir, "--controller-config", config)
    assert rc == 1 and not out["accepted"]
    # every scan, moving or still: the gains gate names the gain, the misfit does not
    # average down like noise
    failed = {g["name"]: g for g in out["gates"] if not g["passed"]}
    assert {"gains", "averaging"} <= set(failed) and "S3 changed by -" in failed["gains"]["reason"]
    # still poses, as before: the noise gate
    rc, out, _ = calibrate_json(rec_dir, "--controller-config", config, "--method", "paper")
    assert rc == 1 and "noise" in {g["name"] for g in out["gates"] if not g["passed"]}


@pytest.mark.slow
@pytest.mark.parametrize("step", STEPS)
def test_killed_while_writing_leaves_the_old_config_or_the_new(offline, tmp_path, step):
    rec_dir, _ = offline
    config = fresh_config(tmp_path / "controller.toml")
    old = config.read_bytes()
    proc = loopcal(
        "calibrate",
        rec_dir,
        "--controller-config",
        config,
        "--write",
        env={"LOOPCAL_KILL_AT": step},
    )
    assert proc.returncode == -signal.SIGKILL, proc.stdout + proc.stderr
    now = config.read_bytes()
    cfg = load_controller_config(config)  # parses: never a partial file
    if STEPS.index(step) < STEPS.index("new-renamed"):
        assert now == old
    else:
        assert now != old and cfg.provenance is not None
        assert abs(cfg.params[INDEX["d01"]] - 97.4) > 0.01


@pytest.mark.slow
def test_window_and_free_set(offline, tmp_path):
    rec_dir, truth = offline
    config = fresh_config(tmp_path / "controller.toml")
    # the geometry is 0.5 mm off the blueprint too: the offsets alone cannot close the loops
    rc, doc, _ = calibrate_json(rec_dir, "--controller-config", config, "--free", "offsets")
    assert list(doc["parameters"]) == ["d01", "d02", "d03", "d04"]
    failed = {g["name"] for g in doc["gates"] if not g["passed"]}
    assert rc == 1 and {"averaging", "gains"} <= failed
    rc, doc, _ = calibrate_json(rec_dir, "--controller-config", config, "--last", "30s")
    assert doc["poses"]["scans"] == 600  # 30 s at 20 Hz
    t = read_recordings(rec_dir).scans["stamp_ns"]
    since, until = (datetime.fromtimestamp(int(t[k]) / 1e9, UTC).isoformat() for k in (200, 600))
    rc, doc, _ = calibrate_json(
        rec_dir, "--controller-config", config, "--since", since, "--until", until
    )
    assert doc["poses"]["scans"] == 400 and rc == 1  # 20 s: too few poses, refused


@pytest.mark.slow
def test_report(offline, tmp_path):
    rec_dir, _ = offline
    config = fresh_config(tmp_path / "controller.toml")
    proc = loopcal_main(
        "calibrate", rec_dir, "--controller-config", config, "--report", tmp_path / "report"
    )
    assert proc.returncode == 0, proc.stderr
    page = (tmp_path / "report" / "index.html").read_text()
    for png in ("changes.png", "residuals.png", "singular_values.png", "workspace.png"):
        data = (tmp_path / "report" / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000 and png in page
    assert "ACCEPTED" in page and "d03" in page
    assert "report: plotting the workspace" in proc.stdout  # long work shows progress
    assert "usable scans, every one fitted" in page


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu"])
def test_replay_round_trip_is_exact_and_calibrates(sessions, tmp_path, transport):
    # 50 s from the middle of a session: the module was powered on before the first scan
    src = trim(sessions[0].directory, tmp_path / "src", 600, 1600)
    player, recorder = replay_and_record(src, tmp_path / "again", transport, 10)
    finish(player, recorder, settle_s=0.5)  # the replay's 1 s tail is 0.1 s at ten times
    a = read_recordings(src).scans
    b = read_recordings(tmp_path / "again").scans
    got = {
        int(c): (int(t), tuple(int(x) for x in k))
        for c, t, k in zip(b["counter64"], b["time64_us"], b["codes"], strict=True)
    }
    for c, t, k in zip(a["counter64"], a["time64_us"], a["codes"], strict=True):
        assert got[int(c)] == (int(t), tuple(int(x) for x in k)), int(c)
    # and the 50 s recorded again over this transport calibrate: every scan counts
    config = fresh_config(tmp_path / "controller.toml")
    rc, doc, err = calibrate_json(tmp_path / "again", "--controller-config", config, "--write")
    assert rc == 0 and doc["written"], (err, doc.get("gates"))
    for name, p in doc["parameters"].items():
        assert abs(p["value"] - sessions[0].truth[INDEX[name]]) <= 3 * p["std"], name


@pytest.mark.slow
def test_bad_input_is_named(tmp_path, offline):
    rec_dir, _ = offline
    config = fresh_config(tmp_path / "controller.toml")
    junk = tmp_path / "junk.mcap"
    junk.write_text("not mcap at all")
    other = tmp_path / "other.mcap"
    from mcap.writer import Writer

    with open(other, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_message(w.register_channel("/camera", "json", 0), 1, b"{}", 1)
        w.finish()
    bad_config = tmp_path / "bad.toml"
    bad_config.write_text(config.read_text().replace("d01 = 97.4", "d01 = 'x'"))
    cases = [
        (["calibrate", tmp_path / "missing.mcap", "--controller-config", config], "no such file"),
        (["calibrate", junk, "--controller-config", config], "not an MCAP file"),
        (["calibrate", other, "--controller-config", config], "not a loopcal recording"),
        (["calibrate", rec_dir, "--controller-config", bad_config], "d01 = 'x' is not a number"),
        (["calibrate", rec_dir], "no controller config"),
        (["calibrate", rec_dir, "--controller-config", config, "--free", "Q9"], "Q9"),
        (
            ["calibrate", rec_dir, "--controller-config", config, "--since", "2099-01-01"],
            "no scans",
        ),
        (["replay", tmp_path / "missing.mcap"], "no such file"),
        (["replay", junk], "not an MCAP file"),
        (["replay", other], "not a loopcal recording"),
    ]
    for args, words in cases:
        proc = loopcal_main(*args)
        assert proc.returncode == 2, (args, proc.stdout, proc.stderr)
        assert words in proc.stderr, (args, proc.stderr)
    bad_time = loopcal_main("calibrate", rec_dir, "--controller-config", config, "--since", "noon")
    assert bad_time.returncode == 2 and "not a time" in bad_time.stderr


@pytest.mark.slow
def test_every_parameter_named_in_json(offline, tmp_path):
    rec_dir, _ = offline
    config = fresh_config(tmp_path / "controller.toml")
    rc, doc, _ = calibrate_json(rec_dir, "--controller-config", config, "--free", "all")
    assert rc == 1  # all 20 cannot be identified: refused, with the reason
    assert set(doc["parameters"]) == set(NAMES)
    assert any("converged" == g["name"] and not g["passed"] for g in doc["gates"])


@pytest.mark.slow
def test_the_worker_units_way_and_the_configs_free_set(offline, tmp_path):
    """--config takes the directory and controller config from the daemon's config (as the
    systemd unit runs it); [calibration].free in the controller config picks the free set."""
    rec_dir, _ = offline
    config = fresh_config(tmp_path / "controller.toml")
    doc = tomlkit.parse(config.read_text())
    # the paper's seven with the ties the simulated mechanism keeps (without them the
    # fit on every scan sees the untied base points' misfit, and refuses: the gains gate)
    doc["calibration"]["free"] = "d01,d02,d03,d04,A1x,A2x,A2y"
    doc["calibration"]["ties"] = ["A3x=-A2x", "A3y=-A2y", "A4x=-A1x"]
    config.write_text(tomlkit.dumps(doc))
    daemon_toml = tmp_path / "daemon.toml"
    daemon_toml.write_text(
        f'[daq]\nurl = "modbus-tcp://10.0.0.9"\n[recording]\n'
        f'directory = "{rec_dir}"\n[controller]\nconfig = "{config}"\n'
    )
    rc, doc, err = calibrate_json("--config", daemon_toml, "--last", "1h")
    assert rc == 0, err
    assert list(doc["parameters"]) == ["d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"]
    assert doc["config"] == str(config)


@pytest.mark.slow
def test_a_cut_recording_with_faults_and_gaps(offline, tmp_path):
    """A file cut short by a crash, with a sensor fault and a gap in it: the scans around
    them are dropped and counted, and the rest still calibrates."""
    from loopcal.daemon import recording as rec_mod

    rec_dir, _ = offline
    rows = read_recordings(rec_dir).scans.copy()
    rows["status"][300:340] |= 1 << 5  # sensor 2 faulted for 2 s
    rows["codes"][300:340, 1] = 4095
    rows["missed"][900] = 3  # three scans lost before this one
    meta = rec_mod.metadata_records(device={}, controller={}, command="test")
    w, _ = write_rows(tmp_path / "cut.mcap", rows, close=False, metadata=meta)
    size = w.durable_size
    w.abandon()  # no summary: as after a crash
    assert (tmp_path / "cut.mcap").stat().st_size == size
    config = fresh_config(tmp_path / "controller.toml")
    rc, doc, err = calibrate_json(tmp_path / "cut.mcap", "--controller-config", config)
    assert "no summary" in err  # said, not hidden
    assert doc["poses"]["scans"] == len(rows)
    dropped = doc["poses"]["dropped_scans"]
    assert dropped["channel at the rail or faulted"] == 40
    assert dropped["next to a gap or restart"] == 10
    assert rc == 0, doc["gates"]


def _locked_by_someone(config) -> bool:
    """Whether another writer holds the config's lock (the writers' own lock, not waited for)."""
    try:
        with durable.locked(config, timeout=0):
            return False
    except durable.Busy:
        return True


@pytest.mark.slow
def test_two_writers_at_once_never_lose_an_update(offline, tmp_path):
    """A holds the config's lock (paused right after taking it); B starts then, reads the
    old config, calibrates and waits for the lock; A writes; B must see that the file
    changed and refuse rather than overwrite A's update."""
    rec_dir, _ = offline
    config = fresh_config(tmp_path / "controller.toml")
    original = config.read_bytes()
    a = Proc(["calibrate", str(rec_dir), "--controller-config", str(config), "--write",
              "--json"], env={"LOOPCAL_PAUSE_AT": "locked:8"})  # fmt: skip
    deadline = time.monotonic() + 60
    while not _locked_by_someone(config):
        assert time.monotonic() < deadline and a.proc.poll() is None, a.text
        time.sleep(0.05)
    b = Proc(["calibrate", str(rec_dir), "--controller-config", str(config), "--write",
              "--json"])  # fmt: skip
    assert a.wait(120) == 0, a.text
    assert b.wait(120) == 2, b.text
    assert "changed since the calibration read it" in b.text and "nothing written" in b.text
    prev = list(tmp_path.glob("controller.toml.*.prev"))
    assert len(prev) == 1 and prev[0].read_bytes() == original  # A's backup, and only A's
    assert load_controller_config(config).provenance is not None


@pytest.mark.slow
def test_a_symlinked_config_stays_a_link_and_its_target_is_written(offline, tmp_path):
    rec_dir, _ = offline
    robot = tmp_path / "opt" / "robot"
    robot.mkdir(parents=True)
    target = fresh_config(robot / "config.toml")
    target.chmod(0o640)
    etc = tmp_path / "etc"
    etc.mkdir()
    link = etc / "controller.toml"
    link.symlink_to(target)
    before = target.read_bytes()
    proc = loopcal_main("calibrate", rec_dir, "--controller-config", link, "--write")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert link.is_symlink() and link.resolve() == target
    assert f"through the symlink {link}" in proc.stdout
    assert target.read_bytes() != before and target.stat().st_mode & 0o777 == 0o640
    [prev] = robot.glob("config.toml.*.prev")
    assert prev.read_bytes() == before and not list(etc.glob("*.prev"))
    proc = loopcal_main("init-config", link, "--force")
    assert proc.returncode == 0 and "through the symlink" in proc.stdout, proc.stderr
    assert link.is_symlink() and target.stat().st_mode & 0o777 == 0o640
    assert load_controller_config(link).provenance is None  # the reference config again


@pytest.mark.slow
def test_backups_never_share_a_name(offline, tmp_path):
    from loopcal.daemon.worker.writeback import write_back

    config = fresh_config(tmp_path / "controller.toml")
    written = []
    for k in range(3):  # within the same second
        cfg = load_controller_config(config)
        p = cfg.params.copy()
        p[INDEX["d01"]] += 0.1 * (k + 1)
        written.append(write_back(cfg, p, {"method": "test"}).backup)
    assert len(set(written)) == 3 and all(b.exists() for b in written)


@pytest.mark.slow
def test_json_warnings_name_the_damaged_file(offline, tmp_path):
    import shutil

    from tests.support.mutations import tear_chunk

    rec_dir, _ = offline
    copy = tmp_path / "rec"
    shutil.copytree(rec_dir, copy)
    [path] = sorted(copy.glob("*.mcap"))
    tear_chunk(path, 200)  # a flush's raw chunk
    config = fresh_config(tmp_path / "controller.toml")
    rc, doc, err = calibrate_json(copy, "--controller-config", config)
    assert len(doc["warnings"]) == 1 and str(path) in doc["warnings"][0]
    warning = doc["warnings"][0]
    assert "scan(s) missing" in warning and "(messages of 2026-11-18T" in warning
    assert "warning: " + doc["warnings"][0] in err
    proc = loopcal_main("calibrate", copy, "--controller-config", config)
    assert doc["warnings"][0] in proc.stdout
    assert rc in (0, 1)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("case", "gates"),
    [
        # sensors 1 and 2 wired to each other's channels: nothing closes
        ("swapped channels", {"noise"}),
        # sensor 3's offset steps by 0.6 mm a minute in: no single value fits the session
        ("offset step", {"averaging", "holdout"}),
    ],
)
def test_moving_scans_that_no_mechanism_explains_are_refused(tmp_path, case, gates):
    truth = truth_for(4)
    kwargs = {}
    if case == "swapped channels":

        def swap(codes):
            codes[:, [0, 1]] = codes[:, [1, 0]]

        kwargs["edit"] = swap
    else:
        kwargs["drifts"] = (OffsetDrift("step", 3, 60.0, 0.6),)
    write_session(tmp_path / "rec", HandMoves(4, params=truth, pause_s=PAUSE_S), truth, 120,
                  seed=4, **kwargs)  # fmt: skip
    config = fresh_config(tmp_path / "controller.toml")
    rc, doc, _ = calibrate_json(tmp_path / "rec", "--controller-config", config, "--write")
    failed = {g["name"]: g for g in doc["gates"] if not g["passed"]}
    assert rc == 1 and not doc["accepted"] and not doc["written"]
    assert gates & set(failed) or "converged" in failed, failed
    assert all(g["reason"] and g["advice"] for g in failed.values())
    assert load_controller_config(config).provenance is None


@pytest.mark.slow
def test_too_little_motion_says_for_how_long(offline, tmp_path):
    """Twenty seconds of the session: every channel moved, but not enough to know the
    seven well; the refusal says which way and for about how long to go on."""
    rec_dir, _ = offline
    config = fresh_config(tmp_path / "controller.toml")
    t = read_recordings(rec_dir).scans["stamp_ns"]
    since, until = (datetime.fromtimestamp(int(t[k]) / 1e9, UTC).isoformat() for k in (0, 300))
    rc, doc, _ = calibrate_json(rec_dir, "--controller-config", config, "--since", since,
                                "--until", until)  # fmt: skip
    failed = {g["name"]: g for g in doc["gates"] if not g["passed"]}
    assert rc == 1 and "precision" in failed, doc["gates"]
    m = re.search(r"for about (\d+) s more of such motion", failed["precision"]["advice"])
    assert m and 5 <= int(m.group(1)) <= 600, failed["precision"]


@pytest.mark.slow
def test_a_technician_who_never_pauses_is_calibrated_in_75_seconds(tmp_path):
    """The plate kept moving the whole time: no still poses for the paper's method, and
    every scan for the fit."""
    truth = truth_for(6)
    write_session(tmp_path / "rec", HandMoves(6, params=truth, pause_s=(0.0, 0.05)), truth, 75,
                  seed=6)  # fmt: skip
    config = fresh_config(tmp_path / "controller.toml")
    rc, doc, err = calibrate_json(tmp_path / "rec", "--controller-config", config)
    assert rc == 0 and doc["accepted"] and doc["samples"] == "scans", (err, doc["gates"])
    for name, p in doc["parameters"].items():
        assert abs(p["value"] - truth[INDEX[name]]) <= 3 * p["std"], name
    rc, doc, _ = calibrate_json(tmp_path / "rec", "--controller-config", config,
                                "--method", "paper")  # fmt: skip
    failed = [g for g in doc["gates"] if not g["passed"]]
    assert rc == 1 and failed[0]["name"] == "poses" and "still poses" in failed[0]["reason"]
