"""Every record of a recording checked (``loopcal verify``, ``loopcal info``'s damage), on real
files written by the daemon's writer and damaged by byte edits: damage confined to the views'
chunks (which the reader skips), their indexes and the summary is named with its byte offset,
topics and time span; Foxglove's TypeScript reader (@mcap/core, with node) refuses the same
files, and every file it refuses we name damaged; a single changed byte anywhere in a closed
file is named, or the file still reads to the very same messages."""

from __future__ import annotations

import io
import json
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from loopcal.daemon import recording as rec
from loopcal.daemon.inspect.fleet import RobotDay, info_task
from loopcal.daemon.recording.verify import verify_file
from loopcal.daemon.times import span_text
from tests.support.fuzz import examples
from tests.support.js import run_node
from tests.support.mutations import chunk_spans, flip_bits, zero_run
from tests.support.processes import loopcal_main
from tests.support.recordings import write_recording
from tests.support.rows import T0, make_rows

N, PER = 200, 20  # scans, scans per flush: two chunks a flush (raw block and events, views)
VIEWS = ("/joint/state", "/plate/transform")  # the topics of every views chunk but the first
#: summary records: opcode, and the fixed part of a chunk index before its map
_STATISTICS, _CHUNK_INDEX = 0x0B, 0x08


@dataclass(frozen=True)
class Original:
    path: Path
    data: bytes
    views: list  # the chunk indexes (mcap library) of the views chunks, in file order


@pytest.fixture(scope="module")
def original(tmp_path_factory) -> Original:
    path = tmp_path_factory.mktemp("verify") / rec.recording_name(T0)
    write_recording(path, make_rows(N), per=PER)
    data = path.read_bytes()
    summary = make_reader(io.BytesIO(data)).get_summary()
    topic = {c.id: c.topic for c in summary.channels.values()}
    views = [c for c in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
             if {topic[i] for i in c.message_index_offsets} == set(VIEWS)]  # fmt: skip
    assert len(views) == N // PER - 1  # the first views chunk also holds /plate/scene
    return Original(path, data, views)


# ---------------------------------------------------------------------------- byte edits


def _footer(data: bytes) -> tuple[int, int, int]:
    """(footer offset, summary start, summary offsets start)."""
    at = len(data) - 8 - 29
    start, offsets, _crc = struct.unpack_from("<QQI", data, at + 9)
    return at, start, offsets


def _resign(data: bytearray) -> bytes:
    """The summary's CRC made to match again: a consistent summary that says something
    wrong, as a buggy tool would write it (storage damage would leave the CRC failing)."""
    at, start, _ = _footer(data)
    struct.pack_into("<I", data, at + 9 + 16, zlib.crc32(data[start : at + 9 + 16]))
    return bytes(data)


def _summary_records(data: bytes, opcode: int) -> list[int]:
    """Offsets of the summary's records of ``opcode``."""
    at, pos, _ = _footer(data)
    out = []
    while pos < at:
        op, length = struct.unpack_from("<BQ", data, pos)
        if op == opcode:
            out.append(pos)
        pos += 9 + length
    return out


def _chunk_index_at(data: bytes, chunk_offset: int) -> int:
    for pos in _summary_records(data, _CHUNK_INDEX):
        if struct.unpack_from("<Q", data, pos + 9 + 16)[0] == chunk_offset:
            return pos
    raise AssertionError(f"no chunk index for byte {chunk_offset}")


def views_flip(o: Original) -> bytes:
    """A flipped bit in a views chunk's compressed data."""
    c = o.views[3]
    return flip_bits(o.data, [(c.chunk_start_offset + c.chunk_length - 200) * 8 + 5])


def views_zeroed(o: Original) -> bytes:
    """A views chunk zeroed whole, record header included (a torn write)."""
    c = o.views[4]
    return zero_run(o.data, c.chunk_start_offset, c.chunk_length)


def views_torn(o: Original) -> bytes:
    """A views chunk's data zeroed behind its intact record header and fields."""
    c = o.views[2]
    return zero_run(o.data, c.chunk_start_offset + 60, c.chunk_length - 60)


def views_bad_crc(o: Original) -> bytes:
    """A views chunk's CRC field changed (its data intact)."""
    c = o.views[5]
    out = bytearray(o.data)
    out[c.chunk_start_offset + 9 + 24] ^= 0x40
    return bytes(out)


def views_no_crc(o: Original) -> bytes:
    """A views chunk's CRC field zeroed: in our files, damage."""
    c = o.views[5]
    out = bytearray(o.data)
    struct.pack_into("<I", out, c.chunk_start_offset + 9 + 24, 0)
    return bytes(out)


def message_index(o: Original) -> bytes:
    """A /joint/state message index entry pointing elsewhere in its chunk."""
    c = o.views[6]
    channel = next(iter(c.message_index_offsets))  # /joint/state: the first of the chunk
    out = bytearray(o.data)
    entry = c.message_index_offsets[channel] + 9 + 6 + 16 * 4  # the fifth entry
    struct.pack_into("<Q", out, entry + 8, struct.unpack_from("<Q", out, entry + 8)[0] + 3)
    return bytes(out)


def message_index_time(o: Original) -> bytes:
    """A message index entry whose log time is not its message's."""
    c = o.views[6]
    channel = list(c.message_index_offsets)[1]  # /plate/transform
    out = bytearray(o.data)
    entry = c.message_index_offsets[channel] + 9 + 6 + 16 * 2
    struct.pack_into("<Q", out, entry, struct.unpack_from("<Q", out, entry)[0] + 1_000)
    return bytes(out)


def chunk_index(o: Original) -> bytes:
    """A views chunk's index entry pointing 7 bytes into the chunk, the summary's CRC made to
    match (a consistent, wrong index)."""
    c = o.views[1]
    out = bytearray(o.data)
    struct.pack_into("<Q", out, _chunk_index_at(o.data, c.chunk_start_offset) + 9 + 16,
                     c.chunk_start_offset + 7)  # fmt: skip
    return _resign(out)


def chunk_index_flip(o: Original) -> bytes:
    """A flipped bit in a views chunk's index entry (its time span), the CRC left failing."""
    c = o.views[1]
    return flip_bits(o.data, [(_chunk_index_at(o.data, c.chunk_start_offset) + 9 + 8) * 8 + 33])


def statistics(o: Original) -> bytes:
    """The statistics record counting one /joint/state message too many, CRC made to match."""
    (at,) = _summary_records(o.data, _STATISTICS)
    out = bytearray(o.data)
    body = at + 9
    struct.pack_into("<Q", out, body, struct.unpack_from("<Q", out, body)[0] + 1)
    pos = body + 8 + 2 + 4 * 4 + 16
    (map_len,) = struct.unpack_from("<I", out, pos)
    for p in range(pos + 4, pos + 4 + map_len, 10):
        cid, count = struct.unpack_from("<HQ", out, p)
        if cid == 4:  # /joint/state
            struct.pack_into("<Q", out, p + 2, count + 1)
    return _resign(out)


#: name -> (edit, the record named, the topics named, what Foxglove's reader does with it)
MUTANTS: dict[str, tuple[Callable[[Original], bytes], str, tuple[str, ...], str]] = {
    "views-chunk-bit-flip": (views_flip, "chunk", VIEWS, "refuses"),
    "views-chunk-zeroed": (views_zeroed, "chunk", VIEWS, "refuses"),
    "views-chunk-data-zeroed": (views_torn, "chunk", VIEWS, "refuses"),
    "views-chunk-bad-crc": (views_bad_crc, "chunk", VIEWS, "refuses"),
    "views-chunk-crc-zeroed": (views_no_crc, "chunk", VIEWS, "reads"),
    "message-index-offset": (message_index, "message index", ("/joint/state",), "refuses"),
    "message-index-log-time": (
        message_index_time,
        "message index",
        ("/plate/transform",),
        "refuses",
    ),  # fmt: skip
    "chunk-index-offset": (chunk_index, "chunk index", VIEWS, "refuses"),
    "chunk-index-bit-flip": (chunk_index_flip, "chunk index", VIEWS, "reads"),
    "statistics-count": (statistics, "statistics", ("/joint/state",), "reads"),
}


@pytest.fixture(scope="module")
def mutants(original, tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("mutants")
    out = {}
    for name, (edit, *_) in MUTANTS.items():
        data = edit(original)
        assert data != original.data and len(data) == len(original.data), name
        out[name] = d / f"{name}.mcap"
        out[name].write_bytes(data)
    return out


# ---------------------------------------------------------------------------- the tests


@pytest.mark.slow
def test_a_clean_file_checks_out_every_record(original):
    v = verify_file(original.path)
    assert v.ok and v.damaged == [] and v.closed
    assert v.chunks == 2 * N // PER and v.records > 2 * N  # the messages inside chunks too
    assert v.messages["/joint/state"] == N and v.messages["/plate/scene"] == 1
    assert v.messages["/daq/scans"] == N // PER
    proc = loopcal_main("verify", original.path)
    assert proc.returncode == 0, proc.stderr
    assert f"{original.path.name}: ok (" in proc.stdout
    assert "every record checked out" in proc.stdout
    info = loopcal_main("info", original.path)
    assert info.returncode == 0 and "damaged:    none" in info.stdout, info.stdout
    doc = json.loads(loopcal_main("info", original.path, "--json").stdout)
    assert doc["damaged"] == [] and doc["files"][0]["damaged"] == []


@pytest.mark.slow
@pytest.mark.parametrize("name", list(MUTANTS))
def test_views_only_damage_is_named_with_its_topics_and_time_span(name, original, mutants):
    _, record, topics, _ = MUTANTS[name]
    path = mutants[name]
    # the reader skips the views' chunks: it reads every scan and says nothing is wrong
    read = rec.read_recordings(path)
    assert len(read.scans) == N
    v = verify_file(path)
    assert not v.ok, name
    items = [d for d in v.damaged if d.record == record]
    assert items, [d.text() for d in v.damaged]
    d = items[0]
    assert set(topics) <= set(d.topics), d.text()
    if record != "summary":
        assert d.start_ns is not None and T0 <= d.start_ns <= d.end_ns < T0 + N * 50_000_000
        assert span_text(d.start_ns, d.end_ns) in d.text()
    line = d.text()
    assert line.startswith(f"{record} at byte {d.offset} (") and ", ".join(d.topics) in line
    # loopcal info: the damaged line names it; --json lists it
    info = loopcal_main("info", path, "--no-poses")
    assert info.returncode == 0, info.stderr  # info reports (docs/tools.md); verify judges
    assert "damaged:    none" not in info.stdout
    assert f"  {path.name}: {line}" in info.stdout, info.stdout
    doc = json.loads(loopcal_main("info", path, "--no-poses", "--json").stdout)
    listed = [x for x in doc["damaged"] if x["offset"] == d.offset and x["record"] == record]
    assert listed and listed[0]["file"] == str(path)
    assert listed[0]["topics"] == (list(d.topics) or None)
    assert doc["files"][0]["damaged"] == [x.as_json() for x in v.damaged]
    if d.start_ns is not None:
        assert listed[0]["start_ns"] == d.start_ns and listed[0]["start_utc"].startswith("20")
    # loopcal verify: exit 1, the same line
    proc = loopcal_main("verify", path)
    assert proc.returncode == 1 and f"  {line}" in proc.stdout, proc.stdout
    as_json = loopcal_main("verify", path, "--json")
    assert as_json.returncode == 1 and json.loads(as_json.stdout)["ok"] is False


@pytest.mark.slow
@pytest.mark.parametrize("name", list(MUTANTS))
def test_foxglove_refuses_what_we_name_and_we_name_all_it_refuses(name, mutants, node_reader):
    """@mcap/core (as tests/js/read_mcap.mjs uses it: indexed, else record by record) on the
    same file: where it refuses, we name damage (never less strict); where it reads the file
    without a word (statistics it does not check, a CRC of 0 it takes as "not written", a
    summary whose CRC fails, read record by record instead), we still name it."""
    *_, foxglove = MUTANTS[name]
    proc = run_node(node_reader, mutants[name])
    refused = proc.returncode != 0
    assert refused == (foxglove == "refuses"), (proc.returncode, proc.stderr[-500:])
    if refused:
        assert "read_mcap.mjs" in proc.stderr and "Traceback" not in proc.stderr
    assert not verify_file(mutants[name]).ok


def test_a_crashed_file_is_not_closed_and_not_damaged_and_a_cut_record_is(original, tmp_path):
    rows = make_rows(100)
    path = tmp_path / rec.recording_name(T0)
    sizes = write_recording(path, rows, per=PER, close=False)
    v = verify_file(path)
    assert v.ok and not v.closed and v.messages["/joint/state"] == 100
    data = path.read_bytes()
    assert all(verify_file_of(tmp_path, data[:n]).ok for n in sizes)  # cut between flushes
    off, length = chunk_spans(data)[5]  # the third flush's views
    [d] = verify_file_of(tmp_path, data[: off + length // 2]).damaged
    assert (d.record, d.offset) == ("chunk", off) and d.what.startswith("cut off")
    assert d.start_ns == int(rows["stamp_ns"][2 * PER]) and d.topics == ()  # no index says
    [d] = verify_file_of(tmp_path, data[: sizes[2] - 100]).damaged  # its last message index
    assert d.record == "message index" and d.topics == ("/plate/transform",), d.text()
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert verify_file(empty).ok and not verify_file(empty).closed


def verify_file_of(directory: Path, data: bytes):
    path = directory / "cut.mcap"
    path.write_bytes(data)
    return verify_file(path)


def test_a_damaged_footer_of_a_closed_file_is_named(original, tmp_path):
    path = tmp_path / "footer.mcap"
    path.write_bytes(original.data[:-3] + b"\x00\x00\x00")  # the closing magic
    [d] = verify_file(path).damaged
    assert d.record == "footer" and "closed" in d.what


def test_fleet_rows_say_what_was_damaged(original, mutants, tmp_path):
    """``fleet info``'s row of a robot-day (run here without Dask: the task is a plain
    function) names the damaged topics and the scans lost, not only a count."""
    clean = info_task(RobotDay("robot-a", "2026-11-18", (original.path,), None))
    assert clean["damaged_files"] == 0 and clean["damaged_topics"] == ""
    assert clean["scans_lost"] == 0 and clean["damage"] == ""
    day = (original.path, mutants["views-chunk-bit-flip"], mutants["statistics-count"])
    row = info_task(RobotDay("robot-a", "2026-11-18", day, None))
    # the reader lost nothing; it warns of the statistics that count a scan too many
    assert row["damaged_files"] == 2 and row["warnings"] == 1
    assert row["damaged_topics"].split() == sorted(VIEWS)
    assert row["scans_lost"] == 0
    assert "views-chunk-bit-flip.mcap: chunk at byte " in row["damage"]
    assert "statistics-count.mcap: statistics at byte " in row["damage"]
    # a chunk of scans lost: its scans counted
    scans_chunk = tmp_path / rec.recording_name(T0 + 10**12)
    data = bytearray(original.data)
    spans = chunk_spans(original.data)
    k = [off for off, _ in spans].index(original.views[3].chunk_start_offset) - 1
    off, length = spans[k]  # the raw chunk of the same flush: its block and no event
    data[off + length - 30] ^= 0x10
    scans_chunk.write_bytes(bytes(data))
    row = info_task(RobotDay("robot-a", "2026-11-18", (scans_chunk,), None))
    assert row["scans_lost"] == PER and "/daq/scans" in row["damaged_topics"].split()


# ---------------------------------------------------------------------------- any byte


def _messages(data: bytes) -> tuple[list, list]:
    """Every message of a file as (channel topic, sequence, log time, publish time, data):
    record by record (the stream reader, CRCs checked), and through the index (log-time
    order). Raises what the mcap library raises on a file it cannot read."""
    stream = []
    channels: dict[int, str] = {}
    for r in StreamReader(io.BytesIO(data), emit_chunks=False, validate_crcs=True).records:
        if type(r).__name__ == "Channel":
            channels[r.id] = r.topic
        elif type(r).__name__ == "Message":
            stream.append((channels[r.channel_id], r.sequence, r.log_time, r.publish_time,
                           bytes(r.data)))  # fmt: skip
    reader = make_reader(io.BytesIO(data), validate_crcs=True)
    indexed = [(c.topic, m.sequence, m.log_time, m.publish_time, bytes(m.data))
               for _, c, m in reader.iter_messages(log_time_order=False)]  # fmt: skip
    return stream, indexed


@pytest.mark.slow
@settings(max_examples=examples(300), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(at=st.integers(min_value=0), xor=st.integers(min_value=1, max_value=255))
def test_any_changed_byte_is_named_or_changes_no_message(original, tmp_path, at, xor):
    """One byte of a closed file changed, anywhere: verify names damage, or the file still
    reads (record by record and by its index) to the very same messages. A byte where MCAP
    has no check (a metadata value, the header's profile) may change nothing we can see."""
    at %= len(original.data)
    data = bytearray(original.data)
    data[at] ^= xor
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(data))
    v = verify_file(path)
    if not v.ok:
        return
    want = _messages(original.data)
    try:
        got = _messages(bytes(data))
    except Exception as exc:  # noqa: BLE001 - the mcap library refusing is the finding
        pytest.fail(f"byte {at} ^ {xor:#x}: verify found nothing, the mcap library: {exc!r}")
    assert got == want, f"byte {at} ^ {xor:#x}: verify found nothing, the messages differ"


def test_a_changed_metadata_value_is_named_by_the_data_section_crc(original, tmp_path):
    """A metadata value changed in place keeps the record's shape and no CRC of its own
    covers it: the data section's CRC (written since this change) does."""
    assert original.data.count(b"12648430") == 1  # the device's serial, in its metadata
    path = tmp_path / "serial.mcap"
    path.write_bytes(original.data.replace(b"12648430", b"12648431"))
    items = verify_file(path).damaged
    assert [(d.record, d.offset) for d in items] == [("data section", 0)]
    assert "metadata" in items[0].what
    assert verify_file(original.path).damaged == []
