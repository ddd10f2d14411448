"""Recordings open in the TypeScript MCAP reader Foxglove uses (@mcap/core, with node) and
their messages decode with Foxglove's own decoders, to the same values Python reads."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from test_recording_format import T0, make_rows, write_file

from calibration.parameters import NOMINAL
from daemon import recording as rec
from daemon import scans as S
from daemon.events import Event, Level

JS = Path(__file__).parent / "js"


@pytest.fixture(scope="session")
def node_reader() -> list[str]:
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.fail("node and npm are required for the Foxglove reader check (.ci/run installs)")
    if not (JS / "node_modules" / "@mcap" / "core").is_dir():
        subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=JS, check=True, timeout=600,
                       capture_output=True)  # fmt: skip
    return [node, str(JS / "read_mcap.mjs")]


def read_ts(node_reader: list[str], path: Path) -> dict:
    proc = subprocess.run([*node_reader, str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def as_rows(ts_scans: list[dict]) -> np.ndarray:
    rows = S.empty(len(ts_scans))
    for i, s in enumerate(ts_scans):
        for name in S.SCAN_DTYPE.names:
            rows[name][i] = int(s[name]) if isinstance(s[name], str) else s[name]
    return rows


def recording(path: Path) -> tuple[np.ndarray, list[Event]]:
    rows = make_rows(300, start=41)
    rows["status"][10:14] = 1 << 2 | 1 << 6  # channel 3 at the rail with a sensor fault
    rows["codes"][10:14, 2] = 4095
    rows["restarted"][200] = True
    rows["epoch"][200:] = 4
    rows["missed"][120] = 3
    events = [
        Event(int(rows["stamp_ns"][120]), "gap", Level.WARNING, "3 missed", {"missed": 3}),
        Event(int(rows["stamp_ns"][200]), "restart", Level.WARNING, "restart", {"epoch": 4}),
    ]
    w, _ = write_file(path, rows, per=20, events=events)
    w.close()
    return rows, events


def test_a_complete_recording_reads_the_same_in_typescript(tmp_path, node_reader):
    path = tmp_path / rec.recording_name(T0)
    rows, events = recording(path)
    ts = read_ts(node_reader, path)
    py = rec.read_recordings(path)
    assert ts["indexed"] and not ts["truncated"] and ts["trailingBytes"] == 0
    assert ts["header"]["library"].startswith("loopcal ")
    assert ts["schemas"] == {schema: enc for schema, enc, _ in rec.CHANNELS.values()}
    assert {t: c["messageEncoding"] for t, c in ts["channels"].items()} == {
        t: enc for t, (_, _, enc) in rec.CHANNELS.items()
    }
    # every scan, every field, the same in both languages
    got = as_rows(ts["scans"])
    got = got[np.argsort(got["counter64"], kind="stable")]
    assert np.array_equal(got, py.scans) and np.array_equal(py.scans, rows)
    assert [(e["kind"], e["message"]) for e in ts["events"]] == [
        (e.kind, e.message) for e in events
    ]
    assert [log["level"] for log in ts["logs"]] == [3, 3]
    assert ts["metadata"] == py.files[0].metadata
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    counts = summary.statistics.channel_message_counts
    assert ts["counts"] == {summary.channels[i].topic: n for i, n in counts.items()}
    js = rec.joint_states(rows, NOMINAL)
    assert ts["states"]["count"] == 300 and ts["transforms"]["count"] == int(js.pose_ok.sum())
    assert not js.pose_ok[10:14].any()  # a faulted channel: no pose
    assert ts["scene"] == [{"id": "base", "frame_id": "base"}, {"id": "plate", "frame_id": "plate"}]
    # first and last views as Python's ROS 2 decoder reads them
    with open(path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        states = [d for *_, d in r.iter_decoded_messages(topics=[rec.TOPIC_STATE])]
        tfs = [d for *_, d in r.iter_decoded_messages(topics=[rec.TOPIC_TRANSFORM])]
    for ts_msg, py_msg in ((ts["states"]["first"], states[0]), (ts["states"]["last"], states[-1])):
        assert int(ts_msg["counter"]) == py_msg.counter and ts_msg["epoch"] == py_msg.epoch
        assert ts_msg["lengths_mm"] == list(py_msg.lengths_mm)
        assert ts_msg["channel_ok"] == list(py_msg.channel_ok)
        assert ts_msg["timestamp"] == {"sec": py_msg.timestamp.sec,
                                       "nanosec": py_msg.timestamp.nanosec}  # fmt: skip
    for ts_msg, py_msg in (
        (ts["transforms"]["first"], tfs[0]),
        (ts["transforms"]["last"], tfs[-1]),
    ):
        q, r = ts_msg["rotation"], py_msg.rotation
        assert [q["x"], q["y"], q["z"], q["w"]] == [r.x, r.y, r.z, r.w]
        assert (ts_msg["parent_frame_id"], ts_msg["child_frame_id"]) == ("base", "plate")


@pytest.mark.parametrize("cut", ["after_a_flush", "mid_chunk"])
def test_a_cut_recording_reads_the_same_in_typescript(tmp_path, node_reader, cut):
    whole = tmp_path / "whole.mcap"
    recording(whole)
    data = whole.read_bytes()
    with open(whole, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes,
                        key=lambda c: c.chunk_start_offset)  # fmt: skip
    c = chunks[8]  # the fifth flush's raw chunk (each flush: a raw chunk, a views chunk)
    n = (
        c.chunk_start_offset
        if cut == "after_a_flush"
        else c.chunk_start_offset + c.chunk_length // 2
    )
    path = tmp_path / "cut.mcap"
    path.write_bytes(data[:n])
    ts = read_ts(node_reader, path)
    py = rec.read_recordings(path)
    assert not ts["indexed"] and ts["truncated"]
    assert len(py) == 80  # four flushes of 20 scans made it
    assert np.array_equal(as_rows(ts["scans"]), py.scans)
    assert ts["counts"]["/joint/state"] == 80
