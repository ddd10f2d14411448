"""The reader on recordings damaged as storage damages them: whatever the bytes, it returns
the intact scans, each once, and says per file what was lost, or raises RecordingError."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer

from loopcal.daemon import recording as rec
from tests.support.fuzz import examples
from tests.support.mutations import (
    ACCEPTABLE,
    MUTATIONS,
    bad_length,
    chunk_spans,
    closed_and_unclosed,
    duplicate_chunk,
    identities,
    judge,
    tear_chunk,
    zero_run,
)
from tests.support.recordings import write_recording, write_rows
from tests.support.rows import T0, make_rows

N = 600  # scans in the fuzzed recording: 30 flushes of 20


@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    """The bytes of the same 600 scans as a closed and as an unclosed (crashed) file."""
    rows = make_rows(N)
    return rows, closed_and_unclosed(rows, tmp_path_factory.mktemp("orig"))


_INT = st.integers(min_value=0, max_value=1 << 24)
MUTATION = st.one_of(
    st.tuples(st.just("flip"), st.lists(st.integers(0, 1 << 26), min_size=1, max_size=8)),
    st.tuples(st.just("truncate"), _INT),
    st.tuples(st.just("zero_run"), _INT, st.integers(1, 8192)),
    st.tuples(st.just("zero_tail"), _INT, st.integers(1, 16384)),
    st.tuples(st.just("dup_chunk"), _INT),
    st.tuples(st.just("swap_chunks"), _INT),
    st.tuples(st.just("bad_length"), _INT, st.integers(0, (1 << 64) - 1)),
    st.tuples(st.just("overwrite"), _INT, st.binary(min_size=1, max_size=64)),
)


_FIXTURES_OK = [HealthCheck.function_scoped_fixture]  # tmp_path is reused: each example rewrites


@pytest.mark.slow
@settings(max_examples=examples(300), deadline=None, suppress_health_check=_FIXTURES_OK)
@given(closed=st.booleans(), mutation=MUTATION)
def test_any_damage_gives_the_intact_scans_once_or_a_declared_error(
    originals, tmp_path, closed, mutation
):
    rows, data = originals
    name, *args = mutation
    damaged = MUTATIONS[name](data[closed], *args)
    path = tmp_path / rec.recording_name(T0)
    path.write_bytes(damaged)
    verdict = judge(rows, path)
    assert verdict in ACCEPTABLE, (name, args, verdict)


@settings(max_examples=examples(60), deadline=None, suppress_health_check=_FIXTURES_OK)
@given(data=st.binary(max_size=200))
def test_any_small_file_is_read_or_refused_by_name(tmp_path, data):
    path = tmp_path / "x.mcap"
    path.write_bytes(data)
    try:
        out = rec.read_recordings(path)
    except rec.RecordingError as exc:
        assert str(path) in str(exc)
    else:
        assert len(out) == 0


@pytest.mark.slow
def test_every_prefix_of_a_recording_start_reads(tmp_path, originals):
    _, data = originals
    path = tmp_path / rec.recording_name(T0)
    for n in range(0, 400):
        path.write_bytes(data[True][:n])
        out = rec.read_recordings(path)  # never OSError(EINVAL), never a traceback
        assert len(out) == 0 and out.files[0].note


def _scan_chunks(data: bytes) -> list[tuple[int, int]]:
    """The chunks of a file that hold scan blocks (the first of each flush's two)."""
    return chunk_spans(data)[0::2]


@pytest.mark.slow
def test_a_zeroed_run_inside_a_chunk_is_reported_with_the_scans_lost(tmp_path):
    rows = make_rows(2628)
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, rows)
    tear_chunk(path, 2 * 40, head=60, tail=10)  # flush 40's scan chunk (each flush has two)
    out = rec.read_recordings(path)
    assert len(out) == 2628 - 20
    [warning] = out.warnings
    assert "20 scan(s) missing: counters 800-819 of epoch 3" in warning, warning
    assert str(path) in warning and "(messages of 2026-11-18T11:07:20.000Z to " in warning
    assert out.files[0].lost_scans == 20


def test_a_zeroed_chunk_header_behind_an_intact_index_is_not_trusted(tmp_path):
    """The summary is intact (its CRC matches) but the bytes at an index offset are not a
    chunk any more: the reader checks opcode and length before reading."""
    rows = make_rows(400)
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, rows)
    data = path.read_bytes()
    off, _ = _scan_chunks(data)[5]
    path.write_bytes(zero_run(data, off, 64))
    out = rec.read_recordings(path)
    assert out.files[0].complete  # read through its index
    assert len(out) == 380 and out.files[0].lost_scans == 20
    assert "no chunk where the index says" in out.warnings[0]


def test_a_written_crc_of_zero_is_damage_in_our_files(tmp_path):
    rows = make_rows(200)
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, rows, close=False)  # read record by record
    data = bytearray(path.read_bytes())
    off, _ = _scan_chunks(bytes(data))[3]
    struct.pack_into("<I", data, off + 9 + 24, 0)  # the chunk's uncompressed CRC
    path.write_bytes(bytes(data))
    out = rec.read_recordings(path)
    assert len(out) == 180 and "chunk without CRC" in out.warnings[0]


def test_another_writer_without_crcs_is_read(tmp_path):
    """Files of other tools may leave CRCs out (0 = not written, as the spec says)."""
    rows = make_rows(100)
    path = tmp_path / "other.mcap"
    with open(path, "wb") as f:
        w = Writer(f, enable_crcs=False)
        w.start(library="some other tool")
        schema, enc, msg_enc = rec.CHANNELS[rec.TOPIC_SCANS]
        sid = w.register_schema(schema, enc, rec.scan_block_msgdef().encode())
        cid = w.register_channel(rec.TOPIC_SCANS, msg_enc, sid)
        for k in range(0, 100, 25):
            block = rows[k : k + 25]
            t = int(block["stamp_ns"][0])
            w.add_message(cid, t, rec.encode_scan_block(block), t)
        w.finish()
    out = rec.read_recordings(path)
    assert np.array_equal(out.scans, rows) and out.warnings == []


def test_a_chunk_written_twice_gives_each_scan_once(tmp_path):
    rows = make_rows(300)
    for closed in (True, False):
        path = tmp_path / rec.recording_name(T0 + closed * 10**9)
        write_recording(path, rows, close=closed)
        path.write_bytes(duplicate_chunk(path.read_bytes(), 2 * 4))  # flush 4's scan chunk
        out = rec.read_recordings(path)
        assert np.array_equal(out.scans, rows)
        assert identities(out.scans) == identities(rows)
        assert len(out.events) == 3  # events once too
        if closed:  # the copy moved the summary: read record by record
            assert "20 duplicated scan(s) dropped" in out.warnings[0]


def test_swapped_chunks_come_back_in_order(tmp_path):
    rows = make_rows(300)
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, rows, close=False)
    data = path.read_bytes()
    spans = chunk_spans(data)
    (a, na), (b, nb) = spans[2], spans[4]  # two flushes' scan chunks
    data = data[:a] + data[b : b + nb] + data[a + na : b] + data[a : a + na] + data[b + nb :]
    path.write_bytes(data)
    out = rec.read_recordings(path)
    assert np.array_equal(out.scans, rows) and out.warnings == []


def test_a_huge_length_field_costs_one_chunk_not_the_file(tmp_path):
    rows = make_rows(300)
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, rows, close=False)
    data = path.read_bytes()
    path.write_bytes(bad_length(data, 2 * 7, (1 << 63) + 12345))  # flush 7's scan chunk
    out = rec.read_recordings(path)
    assert len(out) == 280 and out.files[0].lost_scans == 20


def test_a_torn_tail_of_zeros_says_what_is_lost(tmp_path):
    rows = make_rows(200)
    path = tmp_path / rec.recording_name(T0)
    sizes = write_recording(path, rows, close=False)
    data = path.read_bytes()[: sizes[6] + 100] + bytes(8192)  # ext4 after a power loss
    path.write_bytes(data)
    out = rec.read_recordings(path)
    assert len(out) == 140
    assert "the scans after" in out.warnings[0] and "are lost" in out.warnings[0]


def test_a_damaged_summary_reads_record_by_record(tmp_path):
    rows = make_rows(200)
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, rows)
    data = bytearray(path.read_bytes())
    data[-60] ^= 0x10  # inside the summary
    path.write_bytes(bytes(data))
    out = rec.read_recordings(path)
    assert np.array_equal(out.scans, rows)
    assert not out.files[0].complete
    assert "summary CRC mismatch" in out.warnings[0]
    assert rec.message_time_range(path) is None  # its statistics are not trusted either


def test_the_same_scans_in_two_files_are_kept_once(tmp_path):
    rows = make_rows(300)
    a = tmp_path / rec.recording_name(T0)
    write_recording(a, rows)
    b = tmp_path / rec.recording_name(T0 + 10**9)
    b.write_bytes(a.read_bytes())  # a copy beside it
    out = rec.read_recordings(tmp_path)
    assert np.array_equal(out.scans, rows)
    assert rec.read_recordings([a, a]).files == rec.read_recordings([a]).files


def test_writer_channel_ids_are_what_the_reader_falls_back_on(tmp_path, originals):
    """A file whose first chunk (with the channel records) is lost still gives its scans,
    because our writer always numbers the channels in CHANNELS order from 1."""
    rows, data = originals
    off, length = chunk_spans(data[False])[0]
    path = tmp_path / rec.recording_name(T0)
    path.write_bytes(zero_run(data[False], off, length))
    out = rec.read_recordings(path)
    assert np.array_equal(out.scans, rows[20:])
    # the first 20 are before any scan it has: counted, as at least that many, from the
    # views it kept (each /joint/state names its scan), and said to be no exact count
    assert out.files[0].lost_scans == 20 and out.files[0].lost_unknown
    assert "zeros" in out.warnings[0]
    # and the writer does number them so
    channels = make_reader(io.BytesIO(data[True])).get_summary().channels
    assert {c.topic: i for i, c in channels.items()} == {
        t: i for i, t in enumerate(rec.CHANNELS, start=1)
    }


def test_summary_crc_is_what_the_writer_computes(originals):
    """Guard the CRC range the reader checks: summary start through the footer's second
    offset field."""
    _, data = originals
    d = data[True]
    footer = len(d) - 8 - 29
    start, offsets_at, crc = struct.unpack_from("<QQI", d, footer + 9)
    assert crc == zlib.crc32(d[start : footer + 25]) != 0


def test_parameters_without_forward_kinematics_never_stop_the_raw_scans(tmp_path):
    """A1x = 1e300 passes the vector check but no forward kinematics: the views say so and
    every raw scan is written all the same."""
    from loopcal.calibration.parameters import NOMINAL

    params = NOMINAL.copy()
    params[0] = 1e300
    rows = make_rows(100)
    meta = rec.metadata_records(device={}, controller={}, command="pytest")
    w, _ = write_rows(tmp_path / "v.mcap", rows, params=params, metadata=meta)
    assert w.views_error and w.scans_written == 100
    out = rec.read_recordings(tmp_path / "v.mcap")
    assert np.array_equal(out.scans, rows) and out.warnings == []
    js = rec.joint_states(rows, params)
    assert js.error and not js.pose_ok.any()
