"""Recordings open in the TypeScript MCAP reader Foxglove uses (@mcap/core, with node) and
their messages decode with Foxglove's own decoders to the same values Python reads, whole and
cut short by a crash (tests/support/js/read_mcap.mjs is the TypeScript side)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory

from loopcal.calibration.parameters import NOMINAL
from loopcal.calibration.simulate import simulate_poses
from loopcal.daemon import recording as rec
from loopcal.daemon import scan_rows as S
from loopcal.daemon.events import Event, Level
from loopcal.drivers.ldq412 import volts_to_code
from tests.support.js import read_ts, run_node
from tests.support.rows import T0, rows_from

N, PER = 300, 25  # scans, scans per write() (1.25 s: two blocks per flush)
CUT_AFTER = 5  # the durable copy is taken after this many writes

# the format as docs/recording.md gives it, spelled out rather than taken from daemon.recording
CHANNELS = {
    "/daq/scans": {"schema": "loopcal_msgs/msg/ScanBlock", "messageEncoding": "cdr"},
    "/joint/state": {"schema": "loopcal_msgs/msg/JointState", "messageEncoding": "cdr"},
    "/plate/transform": {"schema": "foxglove_msgs/msg/FrameTransform", "messageEncoding": "cdr"},
    "/loopcal/events": {"schema": "loopcal.Event", "messageEncoding": "json"},
    "/loopcal/log": {"schema": "foxglove.Log", "messageEncoding": "json"},
    "/plate/scene": {"schema": "foxglove.SceneUpdate", "messageEncoding": "json"},
}
SCHEMAS = {
    "loopcal_msgs/msg/ScanBlock": "ros2msg",
    "loopcal_msgs/msg/JointState": "ros2msg",
    "foxglove_msgs/msg/FrameTransform": "ros2msg",
    "loopcal.Event": "jsonschema",
    "foxglove.Log": "jsonschema",
    "foxglove.SceneUpdate": "jsonschema",
}
METADATA = rec.metadata_records(
    device={"model": "LDQ412", "serial": "12648430", "firmware": "2.4"},
    controller={"path": "/etc/loopcal/controller.toml", "d01": "97.4"},
    command="pytest test_recording_foxglove",
)


def as_rows(ts_scans: list[dict]) -> np.ndarray:
    """The scans the TypeScript side decoded, as SCAN_DTYPE rows (64-bit fields come as
    strings, parsed as Python ints)."""
    rows = S.empty(len(ts_scans))
    for i, scan in enumerate(ts_scans):
        assert set(scan) == set(S.SCAN_DTYPE.names)
        for name in S.SCAN_DTYPE.names:
            value = scan[name]
            rows[name][i] = int(value) if isinstance(value, str) else value
    return rows


def varied_rows() -> np.ndarray:
    """N scans at 20 Hz with realistic codes, rails, a gap, a module restart and 64-bit
    counters and device times past the 32-bit wrap."""
    k = np.arange(N)
    restart = 200  # the module restarted: counter and device time start again from 0
    counter = np.where(k < restart, 2**32 - 150 + k, k - restart).astype(np.int64)
    counter[120:restart] += 3  # three scans missed before scan 120
    time_us = counter * 50_000 + np.where(k < restart, 2**33, 7)
    rows = rows_from(time_us, volts_to_code(simulate_poses(N, seed=7).volts), counter=counter)
    rows["stamp_ns"] = T0 + (k + 3 * (k >= 120)) * 50_000_000 + 1_234
    rows["host_ns"] = rows["stamp_ns"] + 2_500_000 + (k % 7) * 100_000
    rows["epoch"] = np.where(k < restart, 3, 4)
    rows["missed"][120] = 3
    rows["restarted"][restart] = True
    rows["status"][restart] = 1 << 9
    rows["time_measured"] = k % 10 == 0
    rows["status_measured"] = k % 3 == 0
    rows["from_fifo"] = k % 50 != 49
    rows["overflow"][250] = True
    rows["status"][250] |= 1 << 8
    for i, ch, code in ((0, 1, 0), (1, 1, 0), (40, 2, 4095), (41, 2, 4095), (42, 0, 4095)):
        rows["status"][i] |= 1 << ch  # at the rail: no pose for this scan
        rows["codes"][i, ch] = code
    rows["status"][90] |= 1 << 7  # sensor fault on channel 4
    return rows


@dataclass
class Written:
    path: Path
    rows: np.ndarray
    events: list[Event]
    cut_path: Path  # the file's first durable_size bytes after CUT_AFTER writes
    cut_scans: int


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> Written:
    d = tmp_path_factory.mktemp("foxglove")
    rows = varied_rows()
    stamp = rows["stamp_ns"]
    events = [
        Event(int(stamp[0]), "recorder_start", Level.INFO, "recording started", {"pid": 1}),
        Event(int(stamp[120]), "gap", Level.WARNING, "3 scans missed",
              {"missed": 3, "counter64": int(rows["counter64"][120]), "reason": "timeout"}),
        Event(int(stamp[200]), "restart", Level.WARNING, "module restarted", {"epoch": 4}),
    ]  # fmt: skip
    path = d / rec.recording_name(T0)
    cut_path = d / "cut-after-write.mcap"
    w = rec.RecordingWriter(path, metadata=METADATA, params=NOMINAL, fsync=False)
    cut_scans = 0
    for n, k in enumerate(range(0, N, PER), start=1):
        lo, hi = stamp[k], stamp[min(k + PER, N) - 1]
        w.write(rows[k : k + PER], [e for e in events if lo <= e.stamp_ns <= hi])
        if n == CUT_AFTER:  # what a crash right now would leave on disk
            cut_path.write_bytes(path.read_bytes()[: w.durable_size])
            cut_scans = w.scans_written
    w.close()
    return Written(path, rows, events, cut_path, cut_scans)


@pytest.fixture(scope="module")
def ts(written, node_reader) -> dict:
    return read_ts(node_reader, written.path)


@pytest.fixture(scope="module")
def py(written) -> rec.Recording:
    return rec.read_recordings(written.path)


@pytest.mark.slow
def test_a_complete_recording_opens_indexed_with_the_documented_channels(ts, py, written):
    assert ts["indexed"] and not ts["truncated"]
    assert ts["header"]["profile"] == "" and ts["header"]["library"].startswith("loopcal ")
    assert ts["schemas"] == SCHEMAS
    assert ts["channels"] == CHANNELS
    assert ts["metadata"] == py.files[0].metadata == METADATA
    assert py.files[0].complete
    with open(written.path, "rb") as f:
        summary = make_reader(f).get_summary()
    counts = summary.statistics.channel_message_counts
    assert ts["counts"] == {summary.channels[i].topic: n for i, n in counts.items()}


def test_every_scan_decodes_the_same_in_typescript(ts, py, written):
    assert ts["trailingBytes"] == 0  # no message has bytes its schema does not account for
    assert np.array_equal(as_rows(ts["scans"]), py.scans)
    assert np.array_equal(py.scans, written.rows)
    assert ts["counts"]["/daq/scans"] > N // PER  # the blocks split at second boundaries


def test_events_and_log_lines_read_the_same(ts, py, written):
    assert ts["events"] == [e.to_json() for e in written.events]
    assert [(e["kind"], e["message"]) for e in ts["events"]] == [
        (e.kind, e.message) for e in py.events
    ]
    assert [(log["level"], log["message"]) for log in ts["logs"]] == [
        (int(e.level), f"{e.kind}: {e.message}") for e in written.events
    ]


def _same(ts_value, py_value) -> bool:
    """A TypeScript-decoded field (JSON) equals the field mcap_ros2 decoded."""
    if hasattr(py_value, "__slots__") or hasattr(py_value, "__dict__"):
        return isinstance(ts_value, dict) and all(
            _same(v, getattr(py_value, k)) for k, v in ts_value.items()
        )
    if isinstance(py_value, (list, tuple, np.ndarray)):
        return len(ts_value) == len(py_value) and all(map(_same, ts_value, py_value))
    if isinstance(py_value, float):
        return np.array_equal(float(ts_value), py_value, equal_nan=True)
    if isinstance(py_value, bool):
        return ts_value is py_value
    if isinstance(py_value, int):
        return int(ts_value) == py_value
    return ts_value == py_value


def test_joint_states_and_transforms_match_the_python_ros2_decoder(ts, written):
    js = rec.joint_states(written.rows, NOMINAL)
    assert not js.pose_ok[[0, 1, 40, 41, 42, 90]].any() and js.pose_ok.sum() > N // 2
    assert ts["states"]["count"] == N == ts["counts"]["/joint/state"]
    assert ts["transforms"]["count"] == int(js.pose_ok.sum()) == ts["counts"]["/plate/transform"]
    with open(written.path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        states = [m for *_, m in r.iter_decoded_messages(topics=[rec.TOPIC_STATE])]
        tfs = [m for *_, m in r.iter_decoded_messages(topics=[rec.TOPIC_TRANSFORM])]
    fields = {"timestamp", "epoch", "counter", "volts", "lengths_mm", "channel_ok", "pose_ok",
              "euler_zyz_deg", "tilt_deg", "swivel_deg", "closure_rms_mm"}  # fmt: skip
    for got, want in ((ts["states"]["first"], states[0]), (ts["states"]["last"], states[-1])):
        assert set(got) == fields and _same(got, want), (got, want)
    assert ts["states"]["first"]["pose_ok"] is False  # scan 0 is at the rail: NaN views
    assert ts["states"]["first"]["euler_zyz_deg"] == ["NaN"] * 3
    assert ts["states"]["last"]["counter"] == str(written.rows["counter64"][-1])
    for got, want in ((ts["transforms"]["first"], tfs[0]), (ts["transforms"]["last"], tfs[-1])):
        assert _same(got, want), (got, want)
        assert set(got) == {"timestamp", "parent_frame_id", "child_frame_id", "translation",
                            "rotation"}  # fmt: skip
        assert (got["parent_frame_id"], got["child_frame_id"]) == ("base", "plate")
        assert set(got["rotation"]) == {"x", "y", "z", "w"}
    sec, nanosec = divmod(int(written.rows["stamp_ns"][np.flatnonzero(js.pose_ok)[0]]), 10**9)
    assert ts["transforms"]["first"]["timestamp"] == {"sec": sec, "nanosec": nanosec}
    assert ts["scene"] == [{"id": "base", "frame_id": "base"}, {"id": "plate", "frame_id": "plate"}]


def test_the_json_schemas_are_ones_foxglove_can_parse(ts):
    # Foxglove builds datatypes from each jsonschema channel's schema (parseJsonSchema in its
    # mcap-support package) and drops the channel with "Error in topic ..." if that throws; it
    # iterates Object.entries(schema.properties) of every object, so an object schema without
    # "properties" (a free-form object) throws "Cannot convert undefined or null to object".
    errors = [e for errs in ts["jsonSchemaErrors"].values() for e in errs]
    assert not errors, "Foxglove's parseJsonSchema would reject:\n" + "\n".join(errors)


@pytest.mark.slow
@pytest.mark.parametrize("cut", ["after_a_write", "mid_file"])
def test_a_cut_recording_streams_the_same_in_typescript(tmp_path, node_reader, written, py, cut):
    if cut == "after_a_write":
        path, leftover = written.cut_path, False
    else:  # halfway through the middle chunk: a crash while the kernel wrote it
        with open(written.path, "rb") as f:
            chunks = sorted(make_reader(f).get_summary().chunk_indexes,
                            key=lambda c: c.chunk_start_offset)  # fmt: skip
        c = chunks[len(chunks) // 2]
        path, leftover = tmp_path / "cut-mid-file.mcap", True
        path.write_bytes(written.path.read_bytes()[: c.chunk_start_offset + c.chunk_length // 2])
    ts = read_ts(node_reader, path)
    cut_py = rec.read_recordings(path)
    assert not ts["indexed"] and ts["truncated"]
    assert (ts["leftoverBytes"] > 0) is leftover  # an incomplete record at the end, or none
    assert not cut_py.files[0].complete
    assert 0 < len(cut_py) < N
    assert np.array_equal(cut_py.scans, py.scans[: len(cut_py)])  # a prefix of the whole
    assert np.array_equal(as_rows(ts["scans"]), cut_py.scans)
    assert ts["metadata"] == METADATA and ts["channels"] == CHANNELS
    assert ts["events"] == [e.to_json() for e in cut_py.events]
    assert ts["states"]["count"] == len(cut_py)  # the views chunk of every flush read
    if cut == "after_a_write":
        assert len(cut_py) == written.cut_scans == CUT_AFTER * PER


@pytest.mark.slow
def test_the_reader_fails_loudly_on_what_it_cannot_read(tmp_path, node_reader):
    not_mcap = tmp_path / "not.mcap"
    not_mcap.write_bytes(b"PAR1 this is not an MCAP file at all")
    proc = run_node(node_reader, not_mcap)
    assert proc.returncode != 0 and "magic" in proc.stderr.lower(), proc.stderr
    bad = tmp_path / "bad-block.mcap"
    with open(bad, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="pytest")
        sid = w.register_schema(rec.SCAN_BLOCK_SCHEMA, "ros2msg", rec.scan_block_msgdef().encode())
        cid = w.register_channel(rec.TOPIC_SCANS, "cdr", sid)
        # a block that says it holds 5 scans and holds none
        w.add_message(cid, T0, b"\x00\x01\x00\x00\x05\x00\x00\x00", T0)
        w.finish()
    proc = run_node(node_reader, bad)
    assert proc.returncode != 0 and "/daq/scans" in proc.stderr, proc.stderr
