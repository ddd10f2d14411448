"""``loopcal export``: a recording whose views were dropped by compaction made again, with
every view, from its raw scans, at the file's own controller config or at
``--controller-config``; never over an existing file; bad input exits 2 naming it; damage
exits 1; ``--json`` says what became of each file. Real files; a subprocess where one is killed."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from numpy.lib.recfunctions import repack_fields

from loopcal.calibration.parameters import INDEX, NOMINAL
from loopcal.daemon import recording as rec
from loopcal.daemon.config.controller import (
    load_controller_config,
    nominal_config,
    write_initial_config,
)
from loopcal.daemon.events import Event, Level
from loopcal.daemon.recording.compact import compact
from loopcal.daemon.version import loopcal_version
from tests.support.js import read_ts
from tests.support.mutations import tear_chunk
from tests.support.processes import fresh_config, loopcal, loopcal_main
from tests.support.recordings import not_recordings, write_recording, write_rows
from tests.support.rows import T0, make_rows
from tests.support.sessions import hand_rows

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

VIEWS = (rec.TOPIC_STATE, rec.TOPIC_TRANSFORM, rec.TOPIC_SCENE)


def _events(rows: np.ndarray, per: int = 20) -> list[Event]:
    """write_recording's events: one every 100 scans."""
    return [Event(int(rows["stamp_ns"][k]), "gap", Level.WARNING, f"test {k}", {"k": k})
            for k in range(0, len(rows), per) if k % 100 == 0]  # fmt: skip


def _recorded(directory: Path, rows: np.ndarray, params: np.ndarray = NOMINAL) -> Path:
    """A recording as the recorder writes it: its controller_config record the full one of
    a config at ``params`` (what ControllerConfig.as_metadata gives)."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / rec.recording_name(int(rows["stamp_ns"][0]))
    controller = nominal_config().as_metadata()
    controller.update({n: repr(float(params[i])) for n, i in INDEX.items()})
    meta = rec.metadata_records(device={"model": "LDQ412", "serial": "12648430"},
                                controller=controller, command="pytest")  # fmt: skip
    write_rows(path, rows, events=_events(rows), metadata=meta, params=params, fsync=False)
    return path


def _by_write_recording(directory: Path, rows: np.ndarray) -> Path:
    """write_recording's file: at NOMINAL, but its controller_config record holds d01 alone."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / rec.recording_name(int(rows["stamp_ns"][0]))
    write_recording(path, rows)
    return path


def _dropped_copy(original: Path, directory: Path) -> Path:
    """A copy of ``original`` compacted without its views."""
    directory.mkdir(parents=True, exist_ok=True)
    copy = directory / original.name
    shutil.copyfile(original, copy)
    r = compact(copy, drop_views=True)
    assert r.done, r
    meta = rec.read_recordings(copy).files[0].metadata["loopcal"]
    assert meta["views"] == "dropped"
    return copy


def _views(path: Path) -> dict[str, list[tuple[int, int, int, bytes]]]:
    """(log time, publish time, sequence, data) of every view message, by the mcap library."""
    out: dict[str, list] = {t: [] for t in VIEWS}
    with open(path, "rb") as f:
        for _, channel, m in make_reader(f).iter_messages(topics=list(VIEWS),
                                                          log_time_order=True):  # fmt: skip
            out[channel.topic].append((m.log_time, m.publish_time, m.sequence, m.data))
    return out


def _scan_bytes(path: Path) -> bytes:
    return repack_fields(rec.read_recordings(path).scans).tobytes()


def _export(*argv: str | Path, env: dict | None = None):
    # a kill point (env) needs a process of its own; anything else runs in this one
    return loopcal("export", *argv, env=env, timeout=120) if env else loopcal_main("export", *argv)


def _bad_input(proc, words: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith("loopcal export: error: ")]
    assert errors and words in errors[0], proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("params_from", ["record", "--controller-config"])
def test_views_dropped_are_made_again_as_recorded(tmp_path, node_reader, params_from):
    rows = hand_rows(2400)  # two minutes at 20 Hz: three batches of a minute
    if params_from == "record":
        original = _recorded(tmp_path / "orig", rows)
        extra: list[str | Path] = []
    else:  # write_recording's record cannot give the parameters: the config gives them
        original = _by_write_recording(tmp_path / "orig", rows)
        extra = ["--controller-config", fresh_config(tmp_path / "controller.toml")]
    copy = _dropped_copy(original, tmp_path / "archive")
    assert not _views(copy)[rec.TOPIC_STATE] and not _views(copy)[rec.TOPIC_TRANSFORM]
    out = tmp_path / "out" / "deeper"
    proc = _export(copy, "--out", out, *extra)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    exported = out / original.name
    assert f"{copy} -> {exported}: 2,400 scans" in proc.stdout
    assert sorted(p.name for p in out.iterdir()) == [original.name]  # no temporary left

    want, got = _views(original), _views(exported)
    assert len(want[rec.TOPIC_STATE]) == 2400 and len(want[rec.TOPIC_SCENE]) == 1
    assert 0 < len(want[rec.TOPIC_TRANSFORM]) <= 2400
    for topic in VIEWS:
        assert got[topic] == want[topic], topic
    assert _scan_bytes(exported) == _scan_bytes(original)  # bit for bit

    back, before = rec.read_recordings(exported), rec.read_recordings(original)
    assert [e.to_json() for e in back.events] == [e.to_json() for e in before.events]
    f = back.files[0]
    assert f.complete and f.intact and not f.warning
    meta, orig_meta = f.metadata, before.files[0].metadata
    assert meta["loopcal"]["format"] == rec.FORMAT_VERSION
    assert meta["loopcal"]["exported_from"] == os.path.abspath(copy)
    assert meta["loopcal"]["exported_utc"]
    for key in ("views", "scans", "views_dropped_utc", "compacted_utc", "chunk_span_s"):
        assert key not in meta["loopcal"]
    assert {k: v for k, v in meta["loopcal"].items()
            if not k.startswith("exported_")} == orig_meta["loopcal"]  # fmt: skip
    assert meta["device"] == orig_meta["device"]
    if params_from == "record":
        assert meta["controller_config"] == orig_meta["controller_config"]
    else:
        cfg = load_controller_config(tmp_path / "controller.toml")
        assert meta["controller_config"] == cfg.as_metadata()

    verify = loopcal_main("verify", exported)  # every record checks out
    assert verify.returncode == 0, verify.stdout + verify.stderr
    ts = read_ts(node_reader, exported)  # Foxglove's TypeScript reader reads it
    assert ts["indexed"] and not ts["truncated"]
    assert ts["counts"][rec.TOPIC_STATE] == 2400 and len(ts["scans"]) == 2400
    assert ts["counts"][rec.TOPIC_TRANSFORM] == len(want[rec.TOPIC_TRANSFORM])
    assert ts["counts"][rec.TOPIC_SCENE] == 1 and ts["scene"]
    assert len(ts["events"]) == len(before.events) == len(ts["logs"])


def test_the_controller_config_given_overrides_the_record(tmp_path):
    rows = hand_rows(600)
    original = _recorded(tmp_path / "orig", rows)  # recorded at NOMINAL
    copy = _dropped_copy(original, tmp_path / "archive")
    moved = NOMINAL.copy()
    moved[INDEX["d01"]] += 0.5
    other = write_initial_config(tmp_path / "moved.toml", params=moved)
    same = write_initial_config(tmp_path / "same.toml")
    proc = _export(copy, "--out", tmp_path / "moved", "--controller-config", other)
    assert proc.returncode == 0, proc.stderr
    proc = _export(copy, "--out", tmp_path / "same", "--controller-config", same)
    assert proc.returncode == 0, proc.stderr
    want = _views(original)
    at_moved = _views(tmp_path / "moved" / original.name)
    at_same = _views(tmp_path / "same" / original.name)
    assert at_same == want
    # another d01: other lengths of actuator 1 in every /joint/state, other poses
    assert len(at_moved[rec.TOPIC_STATE]) == len(want[rec.TOPIC_STATE])
    assert all(g[3] != w[3] for g, w in zip(at_moved[rec.TOPIC_STATE], want[rec.TOPIC_STATE],
                                            strict=True))  # fmt: skip
    assert [m[:3] for m in at_moved[rec.TOPIC_STATE]] == [m[:3] for m in want[rec.TOPIC_STATE]]
    assert at_moved[rec.TOPIC_TRANSFORM] != want[rec.TOPIC_TRANSFORM]
    assert at_moved[rec.TOPIC_SCENE] == want[rec.TOPIC_SCENE]  # d01 is no geometry of the scene
    assert _scan_bytes(tmp_path / "moved" / original.name) == _scan_bytes(original)
    meta = rec.read_recordings(tmp_path / "moved" / original.name).files[0].metadata
    assert meta["controller_config"] == load_controller_config(other).as_metadata()
    assert float(meta["controller_config"]["d01"]) == moved[INDEX["d01"]]


def test_a_file_whose_record_gives_no_parameters_is_refused_by_name(tmp_path):
    good = _recorded(tmp_path / "in", make_rows(300))
    bare = _by_write_recording(tmp_path / "in", make_rows(300, t0=T0 + 10**12))
    out = tmp_path / "out"
    proc = _export(tmp_path / "in", "--out", out)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert f"{bare}: not exported: its controller_config record lacks A1x" in proc.stderr
    assert "--controller-config" in proc.stderr and "Traceback" not in proc.stderr
    assert sorted(p.name for p in out.iterdir()) == [good.name]  # the other one exported


def test_an_existing_output_file_is_refused_and_left_as_it_was(tmp_path):
    a = _recorded(tmp_path / "in", make_rows(300))
    b = _recorded(tmp_path / "in", make_rows(300, t0=T0 + 10**12))
    out = tmp_path / "out"
    out.mkdir()
    there = out / b.name
    there.write_bytes(b"someone's file\n")
    before = there.read_bytes()
    for argv in ([a, b], [tmp_path / "in"], [b, "--json"]):
        proc = _export(*argv, "--out", out)
        _bad_input(proc, f"{there}: exists")
        assert proc.stdout == ""
        assert there.read_bytes() == before
        assert sorted(p.name for p in out.iterdir()) == [b.name]  # nothing else written
    # --out the recordings' own directory: every output is its input
    _bad_input(_export(a, "--out", tmp_path / "in"), f"{tmp_path / 'in' / a.name}: exists")
    assert rec.read_recordings(a).files[0].intact


def test_bad_input_exits_2_naming_it(tmp_path):
    good = _recorded(tmp_path / "in", make_rows(300))
    strangers = not_recordings(tmp_path)
    text = tmp_path / "x.mcap"
    twin = _recorded(tmp_path / "twin", make_rows(300))  # the same name as ``good``
    bad_config = tmp_path / "bad.toml"
    bad_config.write_text("[parameters]\nA1x = 1\n")
    out = tmp_path / "out"
    for argv, words in (
        *strangers,
        ([good, text, "--json"], f"{text}: not an MCAP file"),
        ([good, twin], f"both would be exported to {out / good.name}"),
        ([good, "--controller-config", bad_config], f"{bad_config}: [parameters] lacks"),
        ([good, "--controller-config", tmp_path / "no.toml"], f"{tmp_path / 'no.toml'}: no such"),
    ):
        _bad_input(_export(*argv, "--out", out), words)
        assert not out.exists()  # refused before anything was written
    _bad_input(_export(good, "--out", text), f"--out {text}: exists and is not a directory")
    _bad_input(_export(good, "--out", ""), "an empty path")
    proc = _export(good)
    assert proc.returncode == 2 and "loopcal export: error: " in proc.stderr  # --out required


def test_json_says_what_became_of_each_file_and_damage_exits_1(tmp_path):
    good = _recorded(tmp_path / "in", make_rows(600))
    damaged = _recorded(tmp_path / "in", make_rows(600, t0=T0 + 10**12))
    tear_chunk(damaged, 4)  # the scans of one flush lost
    bare = _by_write_recording(tmp_path / "in", make_rows(300, t0=T0 + 2 * 10**12))
    out = tmp_path / "out"
    proc = _export(tmp_path / "in", "--out", out, "--json")
    assert proc.returncode == 1, proc.stderr
    doc = json.loads(proc.stdout)
    assert set(doc) == {"files", "failed"} and doc["failed"] == 2
    assert [f["path"] for f in doc["files"]] == [str(good), str(damaged), str(bare)]
    for f in doc["files"]:
        assert set(f) == {"path", "out", "scans", "views", "warning", "error"}
    g, d, b = doc["files"]
    poses = len(_views(good)[rec.TOPIC_TRANSFORM])
    assert g == {"path": str(good), "out": str(out / good.name), "scans": 600,
                 "views": {rec.TOPIC_STATE: 600, rec.TOPIC_TRANSFORM: poses, rec.TOPIC_SCENE: 1},
                 "warning": None, "error": None}  # fmt: skip
    assert d["out"] == str(out / damaged.name) and d["error"] is None
    assert d["warning"].startswith(f"{damaged}: ") and 0 < d["scans"] < 600
    assert d["views"][rec.TOPIC_STATE] == d["scans"]
    assert b["out"] is None and str(bare) in b["error"] and b["views"] == {}
    # the damaged file's export holds what it held, no damage in it, and still says which
    # scans are missing (their counters' gap)
    back = rec.read_recordings(out / damaged.name)
    assert len(back.scans) == d["scans"] and not back.files[0].damage
    assert back.files[0].lost_scans == 600 - d["scans"]
    assert _scan_bytes(out / damaged.name) == _scan_bytes(damaged)
    # without --json: the same, for people; the warning on stderr
    proc = _export(damaged, "--out", tmp_path / "again")
    assert proc.returncode == 1
    assert f"loopcal export: warning: {d['warning']}" in proc.stderr


def test_a_killed_export_leaves_no_file_under_the_real_name(tmp_path):
    original = _recorded(tmp_path / "in", make_rows(600))
    out = tmp_path / "out"
    proc = _export(original, "--out", out, env={"LOOPCAL_KILL_AT": "export-written"})
    assert proc.returncode == -9
    assert [p.name for p in out.iterdir()] == [f".{original.name}.export.tmp"]
    proc = _export(original, "--out", out)  # the next export removes the temporary
    assert proc.returncode == 0, proc.stderr
    assert [p.name for p in out.iterdir()] == [original.name]
    assert _views(out / original.name) == _views(original)


def test_a_file_recorded_by_another_loopcal_is_exported_as_written_by_this_one(tmp_path):
    rows = make_rows(300)
    path = tmp_path / "in" / rec.recording_name(int(rows["stamp_ns"][0]))
    path.parent.mkdir()
    meta = rec.metadata_records(device={"model": "LDQ412"}, command="pytest",
                                controller=nominal_config().as_metadata(),
                                extra={"version": "0.0.1"})  # fmt: skip
    write_rows(path, rows, metadata=meta, fsync=False)
    proc = _export(path, "--out", tmp_path / "out")
    assert proc.returncode == 0, proc.stderr
    exported = tmp_path / "out" / path.name
    record = rec.read_recordings(exported).files[0].metadata["loopcal"]
    assert record["version"] == loopcal_version() and record["recorded_version"] == "0.0.1"
    verify = loopcal_main("verify", exported)  # the header's library and the record agree
    assert verify.returncode == 0, verify.stdout + verify.stderr
