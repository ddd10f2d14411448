"""The recording format on real MCAP files: layout, round trip, crashes, bad input."""

from __future__ import annotations

import os
import shutil
from datetime import timedelta

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory
from scipy.spatial.transform import Rotation

from loopcal.calibration.parameters import NOMINAL
from loopcal.calibration.simulate import simulate_poses
from loopcal.daemon import recording as rec
from loopcal.daemon import scan_rows as S
from loopcal.daemon.events import Event, Level
from loopcal.drivers.ldq412 import volts_to_code
from tests.support.recordings import write_rows
from tests.support.rows import T0, make_rows


def test_scan_rows_are_the_cdr_layout_of_the_scan_message():
    fields = [
        (name, {"bool": "bool"}.get(kind, kind), count) for name, kind, count, _ in S.SCAN_FIELDS
    ]
    cdr = rec.cdr_dtype(fields)
    assert cdr.names == S.SCAN_DTYPE.names
    for name in cdr.names:
        assert cdr.fields[name][1] == S.SCAN_DTYPE.fields[name][1], name
    # rows are 8-aligned, so row k of a block sits at the same offsets as the first
    assert S.SCAN_DTYPE.itemsize % 8 == 0 and cdr.itemsize <= S.SCAN_DTYPE.itemsize


def test_block_round_trip_and_ros2_decoder_agree(tmp_path):
    rng = np.random.default_rng(5)
    rows = make_rows(57)
    rows["counter64"][-1] = 2**64 - 1  # extremes survive
    rows["time64_us"][0] = 2**33 + 5
    rows["status"] = rng.integers(0, 1 << 10, len(rows))
    rows["missed"][7] = 4_000_000_000
    rows["restarted"][3] = rows["overflow"][4] = rows["time_measured"][5] = True
    rows["status_measured"][6] = True
    rows["from_fifo"][8] = False
    data = rec.encode_scan_block(rows)
    assert np.array_equal(rec.decode_scan_blocks([data, rec.encode_scan_block(rows[:0])]), rows)
    with pytest.raises(ValueError, match="bytes, not"):
        rec.decode_scan_blocks([data[:-1]])
    path = tmp_path / "a.mcap"
    w, _ = write_rows(path, rows, per=57, close=False)
    w.close()
    with open(path, "rb") as f:
        msgs = [d for _, ch, _, d in make_reader(f, decoder_factories=[DecoderFactory()])
                .iter_decoded_messages(topics=[rec.TOPIC_SCANS])]  # fmt: skip
    decoded = [s for m in msgs for s in m.scans]
    assert len(decoded) == len(rows)
    for s, r in zip(decoded, rows, strict=True):
        for name in S.SCAN_DTYPE.names:
            want = r[name].tolist()
            got = getattr(s, name)
            assert (list(got) if name == "codes" else got) == want, name


def test_views_decode_with_the_ros2_decoder(tmp_path):
    rows = make_rows(40)
    rows["status"][5] = 1 << 2  # channel 3 at the rail: no pose for that scan
    path = tmp_path / "v.mcap"
    w, _ = write_rows(path, rows, close=False)
    w.close()
    js = rec.joint_states(rows, NOMINAL)
    assert not js.pose_ok[5] and js.pose_ok.sum() >= 35
    with open(path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory()])
        states = [d for *_, d in r.iter_decoded_messages(topics=[rec.TOPIC_STATE])]
        tfs = [d for *_, d in r.iter_decoded_messages(topics=[rec.TOPIC_TRANSFORM])]
    assert len(states) == 40 and len(tfs) == int(js.pose_ok.sum())
    for i, st in enumerate(states):
        assert st.counter == rows["counter64"][i]
        assert st.timestamp.sec * 10**9 + st.timestamp.nanosec == rows["stamp_ns"][i]
        np.testing.assert_allclose(st.lengths_mm, js.lengths[i], atol=1e-4)
        assert list(st.channel_ok) == js.channel_ok[i].tolist()
        assert st.pose_ok == js.pose_ok[i]
    q = js.quat[js.pose_ok]
    for tf, qi in zip(tfs, q, strict=True):
        assert (tf.parent_frame_id, tf.child_frame_id) == ("base", "plate")
        got = [tf.rotation.x, tf.rotation.y, tf.rotation.z, tf.rotation.w]
        np.testing.assert_allclose(got, qi, atol=1e-6)
        assert abs(np.linalg.norm(got) - 1) < 1e-6


def test_the_pose_is_the_orientation_the_codes_came_from():
    ps = simulate_poses(30, seed=2, noise_volts=0.0, quantize=False)
    rows = make_rows(30)
    rows["codes"] = volts_to_code(ps.volts)
    js = rec.joint_states(rows, ps.truth)
    assert js.pose_ok.all()
    err = Rotation.from_quat(js.quat) * Rotation.from_matrix(ps.rotations).inv()
    assert np.degrees(err.magnitude()).max() < 0.05  # 12-bit codes: about 0.01 deg
    assert np.nanmax(js.closure_rms_mm) < 0.01
    rows["codes"][3, 1] = 4095  # channel 2 railed: no pose
    assert not rec.joint_states(rows, ps.truth).pose_ok[3]


def test_complete_file_round_trip(tmp_path):
    rows = make_rows(300, start=1000)
    ev = [
        Event(int(rows["stamp_ns"][50]), "gap", Level.WARNING, "2 missed", {"missed": 2}),
        Event(int(rows["stamp_ns"][250]), "restart", Level.WARNING, "restart", {"epoch": 4}),
    ]
    path = tmp_path / rec.recording_name(T0)
    w, _ = write_rows(path, rows, events=ev, close=False)
    w.close()
    out = rec.read_recordings(path)
    assert np.array_equal(out.scans, rows)
    assert [(e.kind, e.details) for e in out.events] == [
        ("gap", {"missed": 2}),
        ("restart", {"epoch": 4}),
    ]
    f = out.files[0]
    assert f.complete and f.note == "" and f.scans == 300
    assert f.metadata["device"]["serial"] == "12648430"
    assert f.metadata["loopcal"]["format"] == rec.FORMAT_VERSION
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    topics = {c.topic: c for c in summary.channels.values()}
    for topic, (schema, schema_enc, msg_enc) in rec.CHANNELS.items():
        assert topics[topic].message_encoding == msg_enc
        s = summary.schemas[topics[topic].schema_id]
        assert (s.name, s.encoding) == (schema, schema_enc)
    counts = summary.statistics.channel_message_counts
    assert counts[topics[rec.TOPIC_STATE].id] == 300
    assert counts[topics[rec.TOPIC_SCENE].id] == 1
    assert counts[topics[rec.TOPIC_EVENTS].id] == counts[topics[rec.TOPIC_LOG].id] == 2


def test_a_file_cut_anywhere_reads_back_a_prefix(tmp_path):
    rows = make_rows(200)
    path = tmp_path / "whole.mcap"
    w, sizes = write_rows(path, rows, close=False)
    data = path.read_bytes()
    w.close()
    cut = tmp_path / "cut.mcap"
    last = -1
    for n in sorted({*sizes, *range(8, len(data), 997)}):
        cut.write_bytes(data[:n])
        out = rec.read_recordings(cut) if n >= sizes[0] else None
        if out is None:
            continue
        k = len(out)
        assert np.array_equal(out.scans, rows[:k]) and k >= last
        assert not out.files[0].complete and "no summary" in out.files[0].note
        if n in sizes:  # cut exactly where a write was durable: everything up to it
            assert k == 20 * (sizes.index(n) + 1)
        last = k


def test_abandon_cuts_back_to_what_was_durable(tmp_path):
    rows = make_rows(60)
    path = tmp_path / "a.mcap"
    w, sizes = write_rows(path, rows, close=False)
    w._writer.add_message(1, T0, b"junk in the chunk builder", T0)
    os.write(w._file.fileno(), b"half a record")  # as if the disk filled up mid-write
    w.abandon()
    assert path.stat().st_size == sizes[-1]
    assert np.array_equal(rec.read_recordings(path).scans, rows)


def test_many_files_time_window_and_duplicates(tmp_path):
    a = make_rows(100, start=0)
    b = make_rows(100, start=100)
    pa, pb = tmp_path / rec.recording_name(T0), tmp_path / rec.recording_name(T0 + 5 * 10**9)
    write_rows(pa, a)
    # a restarted recorder that read the last polled scan again: its file repeats it
    write_rows(pb, np.concatenate([a[-1:], b]))
    (tmp_path / "notes.txt").write_text("not a recording")
    both = rec.read_recordings(tmp_path)
    assert np.array_equal(both.scans, np.concatenate([a, b]))
    assert [f.path for f in both.files] == [pa, pb]
    win = rec.read_recordings([pb, pa], since=int(a["stamp_ns"][90]), until=int(b["stamp_ns"][10]))
    assert win.scans["counter64"].tolist() == list(range(90, 110))
    late = rec.read_recordings(tmp_path, since=int(b["stamp_ns"][50]))
    assert [f.path for f in late.files] == [pb]  # a file wholly before the window is skipped
    assert late.scans["counter64"].tolist() == list(range(150, 200))
    with pytest.raises(ValueError, match="empty time window"):
        rec.read_recordings(pa, since=T0 + 10, until=T0)


def test_the_last_duration_reads_each_file_once(tmp_path, monkeypatch):
    """last=: the end from a closed file's statistics or from the newest scan of a file
    still being written (read once, cut in memory); whole files before the window skipped."""
    a = make_rows(100, start=0)  # 5 s at 20 Hz
    b = make_rows(100, start=100)
    pa, pb = tmp_path / rec.recording_name(T0), tmp_path / rec.recording_name(T0 + 5 * 10**9)
    write_rows(pa, a)
    reads = []
    real = rec.reader.FileReader.read
    monkeypatch.setattr(rec.reader.FileReader, "read",
                        lambda self: reads.append(self.path) or real(self))  # fmt: skip
    w, _ = write_rows(pb, b, close=False)  # the daemon's current file: no statistics yet
    got = rec.read_recordings(tmp_path, last=timedelta(seconds=2))
    assert got.scans["counter64"].tolist() == list(range(160, 200))  # 2 s up to the newest
    # a datetime's microseconds: where the window began, within a microsecond
    assert abs(got.since_ns - (int(b["stamp_ns"][-1]) + 1000 - 2 * 10**9)) < 1000
    assert reads == [pb]  # the unclosed file once; the closed one, wholly before, not at all
    assert [f.scans for f in got.files] == [40]
    w.close()
    reads.clear()
    closed = rec.read_recordings(tmp_path, last=timedelta(seconds=6))
    assert closed.scans["counter64"].tolist() == list(range(80, 200))
    assert sorted(reads) == [pa, pb]
    until = rec.read_recordings(tmp_path, last=timedelta(seconds=1), until=int(a["stamp_ns"][50]))
    assert until.scans["counter64"].tolist() == list(range(30, 50))
    with pytest.raises(ValueError, match="since or last"):
        rec.read_recordings(tmp_path, since=T0, last=timedelta(seconds=1))
    with pytest.raises(ValueError, match="not a positive duration"):
        rec.read_recordings(tmp_path, last=timedelta(0))


def test_names_sort_by_time():
    times = [T0, T0 + 1000, T0 + 10**9, T0 + 86_400 * 10**9]
    names = [rec.recording_name(t) for t in times]
    assert names == sorted(names)
    assert [rec.name_time_ns(n) for n in names] == times
    assert rec.name_time_ns("other.mcap") is None


def test_bad_input_is_named(tmp_path):
    with pytest.raises(rec.RecordingError, match="no such file"):
        rec.read_recordings([tmp_path / "missing.mcap"])
    junk = tmp_path / "junk.mcap"
    junk.write_text("hello")
    with pytest.raises(rec.RecordingError, match="not an MCAP file"):
        rec.read_recordings(junk)
    other = tmp_path / "other.mcap"
    with open(other, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        w.add_message(w.register_channel("/camera", "json", sid), 1, b"{}", 1)
        w.finish()
    with pytest.raises(rec.RecordingError, match=r"not a loopcal recording.*/camera"):
        rec.read_recordings(other)
    with pytest.raises(rec.RecordingError, match="not a directory"):
        rec.find_recordings(junk)


def test_a_damaged_chunk_is_skipped_and_reported(tmp_path):
    rows = make_rows(100)
    path = tmp_path / "d.mcap"
    w, sizes = write_rows(path, rows, close=False)
    w.close()
    data = bytearray(path.read_bytes())
    with open(path, "rb") as f:
        chunks = sorted(
            make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )
    victim = chunks[2]  # a raw chunk of the second write
    mid = victim.chunk_start_offset + victim.chunk_length - 40
    data[mid] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    out = rec.read_recordings(bad)
    warning = out.files[0].warning
    assert "chunk does not decompress" in warning or "chunk CRC mismatch" in warning
    assert "20 scan(s) missing: counters 20-39 of epoch 3" in warning, warning
    assert out.warnings == [warning] and warning.startswith(str(bad))
    assert len(out) == 80 and np.array_equal(out.scans, np.concatenate([rows[:20], rows[40:]]))
    shutil.copy(path, tmp_path / "ok.mcap")
