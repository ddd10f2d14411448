"""A compacted recording's chunks each hold at most CHUNK_SPAN_NS of it, so that one damaged
byte costs at most that much of its scans (issue 20: one bit used to lose the whole file)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import breakup_chunk

from loopcal.calibration.parameters import NOMINAL
from loopcal.daemon import recording as rec
from loopcal.daemon.events import Event, Level
from loopcal.daemon.recording.columns import decode_columns, is_columns
from loopcal.daemon.recording.compact import CHUNK_SPAN_NS, compact
from tests.support.mutations import chunk_spans, flip_bits
from tests.support.recordings import in_large_chunks, write_recording
from tests.support.rows import T0, make_rows

pytestmark = pytest.mark.timeout(120)

RATE = 20  # make_rows' scans per second
#: the most scans one chunk may hold at make_rows' rate
BOUND_SCANS = CHUNK_SPAN_NS * RATE // 10**9


def _compacted(tmp_path: Path, minutes: float = 5.5) -> tuple[Path, np.ndarray]:
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, make_rows(int(minutes * 60 * RATE)))
    original = rec.read_recordings(path).scans
    assert compact(path).done
    return path, original


def _chunks(path: Path) -> list[tuple[int, int, set[str], list[tuple[str, Message]]]]:
    """(offset, length, topics, [(topic, message)]) of each chunk of a closed file, in file
    order (each chunk's CRC checked)."""
    data = path.read_bytes()
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    topic = {cid: c.topic for cid, c in summary.channels.items()}
    out = []
    for off, length in chunk_spans(data):
        chunk = Chunk.read(ReadDataStream(io.BytesIO(data[off + 9 : off + length])))
        messages = [(topic[r.channel_id], r) for r in breakup_chunk(chunk, validate_crc=True)
                    if isinstance(r, Message)]  # fmt: skip
        out.append((off, length, {t for t, _ in messages}, messages))
    return out


@pytest.mark.slow
def test_every_chunk_of_a_compacted_file_spans_at_most_the_bound(tmp_path):
    path, original = _compacted(tmp_path)
    chunks = _chunks(path)
    scans_seen = 0
    for _, _, topics, messages in chunks:
        times = [m.log_time for _, m in messages]
        assert max(times) - min(times) <= CHUNK_SPAN_NS, topics  # every chunk, views too
        if rec.TOPIC_SCANS in topics:
            blocks = [m.data for t, m in messages if t == rec.TOPIC_SCANS]
            assert len(blocks) == 1 and is_columns(blocks[0])  # a minute, packed
            rows = decode_columns(blocks[0])
            stamps = rows["stamp_ns"].astype(np.int64)
            assert stamps[-1] - stamps[0] < CHUNK_SPAN_NS and len(rows) <= BOUND_SCANS
            scans_seen += len(rows)
            assert topics <= {rec.TOPIC_SCANS, rec.TOPIC_EVENTS, rec.TOPIC_LOG}  # no views
    assert scans_seen == len(original)
    kinds = [rec.TOPIC_SCANS in t for _, _, t, _ in chunks]
    assert kinds == [True, False] * (len(chunks) // 2)  # each minute's views after its scans
    assert len(chunks) == 2 * 6  # 5.5 minutes: six of each
    meta = rec.read_recordings(path).files[0].metadata["loopcal"]
    assert int(meta["chunk_span_s"]) * 10**9 == CHUNK_SPAN_NS and "compacted_utc" in meta


@pytest.mark.slow
def test_one_flipped_bit_in_a_scan_chunk_loses_at_most_the_bound(tmp_path):
    path, original = _compacted(tmp_path)
    data = path.read_bytes()
    scan_chunks = [(off, n) for off, n, topics, _ in _chunks(path) if rec.TOPIC_SCANS in topics]
    assert len(scan_chunks) == 6
    for k, (off, n) in enumerate(scan_chunks):
        for at in (off + 30, off + n // 2, off + n - 2):  # header, data, the data's end
            mutant = tmp_path / "mutant" / path.name
            mutant.parent.mkdir(exist_ok=True)
            mutant.write_bytes(flip_bits(data, [at * 8 + 5]))
            out = rec.read_recordings(mutant)
            info = out.files[0]
            lost = len(original) - info.scans
            assert 0 < lost <= BOUND_SCANS, (k, at, lost)
            assert info.warning and not info.intact
            got = set(out.scans["counter64"].tolist())
            assert got <= set(original["counter64"].tolist())
            missing = original[~np.isin(original["counter64"], list(got))]
            span = int(missing["stamp_ns"][-1]) - int(missing["stamp_ns"][0])
            assert len(missing) == lost and span < CHUNK_SPAN_NS
            if 0 < k < len(scan_chunks) - 1:  # a gap between scans: the reader counts it
                assert info.lost_scans == lost, (k, info.lost, lost)
            else:  # the first or the last minute: the damaged chunk is named, with its span
                (d,) = info.damage
                assert d.offset == off and d.end_ns - d.start_ns < CHUNK_SPAN_NS


@pytest.mark.slow
def test_events_without_scans_are_bounded_too(tmp_path):
    """A module that does not answer for three minutes: events only, their chunks bounded
    as the scans' are."""
    path = tmp_path / rec.recording_name(T0)
    meta = rec.metadata_records(device={"model": "LDQ412"}, controller={}, command="pytest")
    w = rec.RecordingWriter(path, metadata=meta, params=NOMINAL, fsync=False)
    w.write(make_rows(40))
    for s in range(180):
        t = T0 + (2 + s) * 10**9
        w.write(make_rows(0), [Event(t, "disconnect", Level.WARNING, f"no answer {s}", {})])
    w.close()
    before = rec.read_recordings(path)
    assert compact(path).done
    after = rec.read_recordings(path)
    assert [e.to_json() for e in after.events] == [e.to_json() for e in before.events]
    for _, _, topics, messages in _chunks(path):
        times = [m.log_time for _, m in messages]
        assert max(times) - min(times) <= CHUNK_SPAN_NS, topics


@pytest.mark.slow
def test_a_file_compacted_into_chunks_of_4_mib_is_compacted_again(tmp_path):
    """Files compacted by an older loopcal hold an hour in one chunk: the compactor takes
    them again (their loopcal record has no chunk_span_s)."""
    path, original = _compacted(tmp_path, minutes=3)
    old = tmp_path / "old.mcap"
    in_large_chunks(path, old, lambda record: record.pop("chunk_span_s", None))
    old.replace(path)
    assert len([t for _, _, t, _ in _chunks(path) if rec.TOPIC_SCANS in t]) == 1
    r = compact(path)
    assert r.done, r
    after = rec.read_recordings(path)
    assert np.array_equal(after.scans["counter64"], original["counter64"])
    assert after.files[0].metadata["loopcal"]["chunk_span_s"] == str(CHUNK_SPAN_NS // 10**9)
    assert len([t for _, _, t, _ in _chunks(path) if rec.TOPIC_SCANS in t]) == 3
    assert compact(path).reason == "already compact"
