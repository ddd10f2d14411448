"""What a damaged recording file lost, said exactly where the file's records allow it
(issue 20, "nothing laundered"): scans lost at the very start or end of a file where no
counter gap shows them, events lost with a damaged chunk, chunks of a closed file out of
order (read, not lost), and files read with bounded memory (mapped, never copied whole)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from mcap.exceptions import EndOfFile
from mcap.records import MessageIndex
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from loopcal.daemon import recording as rec
from loopcal.daemon.recording.filereader import FileReader
from loopcal.daemon.recording.walk import walk
from tests.support.mutations import chunk_spans, flip_bits, swap_chunks, zero_run
from tests.support.recordings import write_recording, write_rows
from tests.support.rows import T0, make_rows

N, PER = 1457, 75  # 20 flushes (a raw chunk, then a views chunk, each), the last of 32


@pytest.fixture(scope="module")
def rows() -> np.ndarray:
    return make_rows(N, seed=5)


def _written(directory: Path, rows: np.ndarray, *, closed: bool) -> tuple[Path, bytes]:
    path = directory / rec.recording_name(T0)
    path.unlink(missing_ok=True)
    write_recording(path, rows, per=PER, close=closed)
    return path, path.read_bytes()


def _flip_in(data: bytes, k: int) -> bytes:
    off, length = chunk_spans(data)[k]
    return flip_bits(data, [(off + length // 2) * 8])


@pytest.mark.parametrize("closed", [True, False])
def test_one_flipped_bit_in_the_first_chunk_says_the_75_scans_and_the_event_it_lost(
    tmp_path, rows, closed
):
    """No counter gap shows scans lost at a file's start: the views (a chunk of their own)
    and, in a closed file, the statistics record do."""
    path, data = _written(tmp_path, rows, closed=closed)
    path.write_bytes(_flip_in(data, 0))
    out = rec.read_recordings(path)
    [f] = out.files
    assert np.array_equal(out.scans, rows[PER:])
    assert (f.lost_scans, f.lost_unknown, f.lost_events, f.lost_events_unknown) == (
        75,
        "",
        1,
        False,
    )
    assert "75 scan(s) missing: counters 0-74 of epoch 3" in f.warning, f.warning
    assert "1 event(s) lost" in f.warning and "no scan" not in f.warning


def test_the_last_raw_chunk_lost_is_counted_by_its_views(tmp_path, rows):
    path, data = _written(tmp_path, rows, closed=False)
    path.write_bytes(_flip_in(data, -2))  # the last flush's raw chunk
    out = rec.read_recordings(path)
    [f] = out.files
    assert len(out) == N - 32 and f.lost_scans == 32 and not f.lost_unknown
    assert f"32 scan(s) missing: counters {N - 32}-{N - 1} of epoch 3" in f.warning


def test_scans_lost_with_their_views_are_counted_by_the_statistics(tmp_path, rows):
    """Both chunks of the first flush zeroed: a closed file's statistics still count the
    75 scans (their counters unknown)."""
    path, data = _written(tmp_path, rows, closed=True)
    (a, _), (b, nb) = chunk_spans(data)[:2]
    path.write_bytes(zero_run(data, a, b + nb - a))
    [f] = rec.read_recordings(path).files
    assert (f.lost_scans, f.lost_unplaced, f.lost_unknown) == (75, 75, "")
    assert "75 scan(s) missing: 75 whose counters are unknown" in f.warning, f.warning


def test_where_nothing_counts_them_the_loss_is_said_to_be_unknown(tmp_path, rows):
    """The same in a file that was not closed: no record says how many scans the zeroed
    bytes held, and the warning says so rather than 'no scan missing'."""
    path, data = _written(tmp_path, rows, closed=False)
    (a, _), (b, nb) = chunk_spans(data)[:2]
    path.write_bytes(zero_run(data, a, b + nb - a))
    out = rec.read_recordings(path)
    [f] = out.files
    assert len(out) == N - PER and f.lost_scans == 0 and f.lost_unknown
    assert "an unknown number of scans missing: an unknown number before" in f.warning
    assert "no scan lost" not in f.warning and f.lost_events_unknown


def test_a_crash_inside_the_last_raw_chunk_says_the_end_is_lost(tmp_path, rows):
    path, data = _written(tmp_path, rows, closed=False)
    off, length = chunk_spans(data)[-2]
    path.write_bytes(data[: off + length // 2])
    [f] = rec.read_recordings(path).files
    assert f.lost_unknown.startswith("the scans after") and "are lost" in f.warning
    assert f.scans == N - 32


@pytest.mark.slow
def test_a_crash_inside_the_last_views_chunk_loses_nothing(tmp_path, rows):
    path, data = _written(tmp_path, rows, closed=False)
    off, length = chunk_spans(data)[-1]
    path.write_bytes(data[: off + length // 2])
    out = rec.read_recordings(path)
    [f] = out.files
    assert np.array_equal(out.scans, rows)
    assert (f.lost_scans, f.lost_unknown, f.lost_events_unknown) == (0, "", True)
    assert "cut off" in f.warning and "(no scan lost)" in f.warning


@pytest.mark.slow
@pytest.mark.parametrize("k", [0, 1, 7, 20, 37])
def test_intact_chunks_of_a_closed_file_out_of_order_are_all_read(tmp_path, rows, k):
    """Two intact chunks swapped (a raw and a views chunk, or two flushes'): the summary is
    intact and its index no longer matches; every scan and event is read, and the
    mismatch is named as such, not as scans lost (it lost 401 of 1,457, declared)."""
    path, data = _written(tmp_path, rows, closed=True)
    events = rec.read_recordings(path).events
    path.write_bytes(swap_chunks(data, k))
    out = rec.read_recordings(path)
    [f] = out.files
    assert np.array_equal(out.scans, rows) and out.events == events
    assert (f.lost_scans, f.lost_unknown, f.lost_events, f.lost_events_unknown) == (0, "", 0, False)
    assert "the chunk index does not match the chunks" in f.warning, f.warning
    assert "missing" not in f.warning and not f.complete


def test_a_device_is_refused_not_read_forever(tmp_path):
    with pytest.raises(rec.RecordingError, match="not a regular file"):
        FileReader(Path("/dev/zero"), None, None).read()


def _mapped(path: Path) -> bool:
    return str(path) in Path("/proc/self/maps").read_text()


def test_a_closed_file_is_mapped_and_unmapped_before_the_read_returns(tmp_path, rows):
    path, data = _written(tmp_path, rows[:300], closed=True)
    for mutant in (data, _flip_in(data, 2), swap_chunks(data, 3), data[:-3]):
        path.write_bytes(mutant)
        rec.read_recordings(path)
        assert not _mapped(path)
    other = tmp_path / "other.mcap"  # closed, so mapped, and refused: unmapped too
    with open(other, "wb") as f:
        w = Writer(f)
        w.start()
        w.add_message(w.register_channel("/other", "json", 0), 0, b"{}", 0)
        w.finish()
    with pytest.raises(rec.RecordingError, match="not a loopcal recording"):
        rec.read_recordings(other)
    assert not _mapped(other)


def test_a_damaged_format_byte_is_damage_but_another_format_is_refused(tmp_path, rows):
    """7 of the 8 bits of the format's "1" make another character in a record no CRC but
    the data section's covers: when every scan block is this format's, that is one damaged
    byte (every scan read, the damage named); a file of another format is refused."""
    path, data = _written(tmp_path, rows[:300], closed=True)
    fmt = b"\x06\x00\x00\x00format\x01\x00\x00\x00"  # the loopcal record's format field
    assert data.count(fmt + b"1") == 1
    path.write_bytes(data.replace(fmt + b"1", fmt + b"9"))
    out = rec.read_recordings(path)
    assert len(out.scans) == 300 and not out.files[0].intact
    assert any("says format '9'" in d.what for d in out.files[0].damage)
    empty = tmp_path / "empty.mcap"  # nothing in this format's layout: another format
    write_rows(empty, rows[:0], metadata={"loopcal": {"format": "9"}, "device": {},
                                          "controller_config": {}})  # fmt: skip
    newer = "recording format 9, written by a newer loopcal: this one reads formats 1, 2; "
    with pytest.raises(rec.RecordingError, match=newer + "upgrade loopcal"):
        rec.read_recordings(empty)
    # not ASCII digits (not said to be newer), and a hostile length: words, never a crash
    for i, (fmt, said) in enumerate(
        [
            ("x", "recording format x, this loopcal reads formats 1, 2$"),
            ("\u00b2", "recording format \u00b2, this loopcal reads formats"),
            ("9" * 5000, "recording format '9{32}'..., written by a newer loopcal"),
            ("a\x00" * 40, r"recording format 'a\\x00a.*\.\.\., this loopcal reads"),
        ]
    ):
        odd = tmp_path / f"odd{i}.mcap"
        write_rows(
            odd,
            rows[:0],
            metadata={"loopcal": {"format": fmt}, "device": {}, "controller_config": {}},
        )
        with pytest.raises(rec.RecordingError, match=said):
            rec.read_recordings(odd)


def test_an_empty_or_tiny_file_is_read_without_mapping(tmp_path):
    path = tmp_path / rec.recording_name(T0)
    for data in (b"", b"\x89MC"):
        path.write_bytes(data)
        [f] = rec.read_recordings(path).files
        assert f.scans == 0 and "nothing written" in f.note


def test_the_walk_parses_message_indexes_as_the_mcap_library_does(tmp_path, rows):
    """The walk parses message index records itself (they count what a damaged chunk
    held); guard it against the library's parser."""
    path, data = _written(tmp_path, rows[:300], closed=False)
    ours = [r for r in walk(memoryview(data), strict=True, wanted=lambda: None)
            if isinstance(r, MessageIndex)]  # fmt: skip
    stream = StreamReader(io.BytesIO(data), emit_chunks=True)
    theirs = []
    try:
        for r in stream.records:
            if isinstance(r, MessageIndex):
                theirs.append(r)
    except EndOfFile:  # an unclosed file ends after its last record
        pass
    assert len(ours) == len(theirs) > 10
    assert [(r.channel_id, r.records) for r in ours] == [(r.channel_id, r.records) for r in theirs]
