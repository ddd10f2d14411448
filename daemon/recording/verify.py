"""Every record of a recording checked, views included (``loopcal verify``, ``loopcal info``).

The reader (:mod:`~loopcal.daemon.recording.filereader`) reads what it needs, the chunks of
``/daq/scans`` and ``/loopcal/events``, and skips the views' chunks by the chunk index: damage
confined to a views chunk is never seen by it, while Foxglove's reader refuses the file. This
module is the check in the spirit of ``mcap doctor``: it walks the whole file, with the
file's bytes mapped (never read whole into memory; one chunk is decompressed at a time), and
checks

- the magic, the header and (for our files) that the header's library is the one the
  ``loopcal`` metadata names;
- every chunk: its header fields against its length, a CRC written (our writer always writes
  one), decompression to the size it claims, the CRC, and every record inside it (schemas,
  channels, messages: each message on a defined channel, its log time within the chunk's);
- the message indexes after each chunk: every entry pointing at a message of its channel and
  log time, every message of the chunk indexed once;
- every metadata record, and the data end record (its data section CRC when one is written);
- the summary section: its CRC, every record's shape, the schemas and channels against those
  of the data section, every chunk index against the chunk it points to (offset, length,
  times, compression, sizes, message index offsets and length), every chunk in the index,
  the metadata indexes against the metadata records, the summary offsets against the groups
  they point to, the statistics against the counts actually found (per channel, messages,
  chunks, schemas, channels, metadata, times), and the footer (summary start and offsets).

What does not check out is a :class:`Damaged` item: its byte offset and length, the record,
what was wrong, the topics its messages were on (from the chunk index's channel ids, the
message indexes, or the chunk's own records; empty when nothing says) and their time span.
A file not closed (no data end, no footer: a crash, or the file being written) is no damage
in itself; a last record cut off by the end of the file is.

MCAP gives metadata records and the header no CRC of their own: only the data section's
CRC (in the data end record) covers them. Files written since format 1's recorders turned
it on have one; in older files a flipped character in a metadata value that keeps the
record's shape reads as a different value. The header's library
is checked against the ``loopcal`` metadata's version and that record's format against the
format version; other metadata values are taken as they are.
"""

from __future__ import annotations

import bisect
import mmap
import os
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from mcap.opcode import Opcode
from mcap.records import Channel, Footer, Header, Schema, Statistics

from .errors import RecordingError
from .records import (
    MAGIC,
    MAX_CHUNK_BYTES,
    PARSE_ERRORS,
    RECORD_HEAD,
    chunk_header,
    parse_record,
    record_at,
)
from .schemas import CHANNELS, READ_FORMATS

_HEAD = struct.Struct("<BQ")  # opcode, record length
_MESSAGE_FIXED = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # a message record's opcode, length and fixed fields
_INDEX_FIXED = struct.Struct("<QQQQI")  # start, end, chunk offset, chunk length, map bytes
_INDEX_ENTRY = struct.Struct("<HQ")  # channel id, message index offset
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
_FOOTER_BYTES = RECORD_HEAD + 20
_DATA_END_BYTES = RECORD_HEAD + 4
_CRC_PIECE = 1 << 24
#: intact chunks are checked through their message indexes with numpy in batches of this many
#: bytes (decompressed): a file as written has two chunks of some 20 messages each a second
_BATCH_BYTES = 1 << 20  # bytes given to zlib.crc32 at once over the mapped file
_SUMMARY_OPCODES = {Opcode.SCHEMA, Opcode.CHANNEL, Opcode.CHUNK_INDEX, Opcode.ATTACHMENT_INDEX,
                    Opcode.METADATA_INDEX, Opcode.STATISTICS, Opcode.SUMMARY_OFFSET}  # fmt: skip
#: channel ids our writer gives the topics (CHANNELS order, from 1): the topics of a damaged
#: chunk of ours when no index survives to say
_OUR_TOPICS = {i: topic for i, topic in enumerate(CHANNELS, start=1)}


def _name(op: int) -> str:
    try:
        return Opcode(op).name.lower().replace("_", " ")
    except ValueError:
        return f"opcode 0x{op:02x}"


def span_text(start_ns: int | None, end_ns: int | None) -> str:
    """A time span for people: ``2026-11-18 12:00:01.000–12:00:02.950 UTC`` (the date once
    when both ends are on one day); ``""`` when unknown."""
    if start_ns is None or end_ns is None:
        return ""

    def at(ns: int) -> datetime | None:
        try:
            return datetime.fromtimestamp(ns // 1_000_000_000, UTC).replace(
                microsecond=(ns % 1_000_000_000) // 1000
            )
        except (OverflowError, OSError, ValueError):
            return None

    a, b = at(start_ns), at(end_ns)
    if a is None or b is None:
        return f"{start_ns}–{end_ns} ns"
    left = f"{a:%Y-%m-%d %H:%M:%S}.{a.microsecond // 1000:03d}"
    right = f"{b:%H:%M:%S}.{b.microsecond // 1000:03d}"
    if a.date() != b.date():
        right = f"{b:%Y-%m-%d} {right}"
    return f"{left}–{right} UTC"


def _iso(ns: int | None) -> str | None:
    if ns is None:
        return None
    try:
        t = datetime.fromtimestamp(ns // 1_000_000_000, UTC)
    except (OverflowError, OSError, ValueError):
        return None
    return t.replace(microsecond=(ns % 1_000_000_000) // 1000).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class Damaged:
    """One item of a file that did not check out.

    Attributes
    ----------
    offset : int
        Its first byte in the file.
    length : int
        Bytes it spans (0 when unknown).
    record : str
        What lies there: ``chunk``, ``message index``, ``metadata``, ``header``, ``data end``,
        ``chunk index``, ``statistics``, ``metadata index``, ``summary offset``, ``summary``,
        ``footer``, ``records`` (bytes where no record could be read), ``data section``.
    what : str
        What was wrong, for people (e.g. ``"CRC mismatch"``).
    topics : tuple of str, default ()
        The topics of the messages it held or described, sorted; empty when nothing says.
    start_ns : int or None, default None
        Log time of the first message it held or described, ns since the Unix epoch.
    end_ns : int or None, default None
        Log time of the last, likewise.
    messages : int or None, default None
        How many messages it held or described, when an index or the chunk says.
    """

    offset: int
    length: int
    record: str
    what: str
    topics: tuple[str, ...] = ()
    start_ns: int | None = None
    end_ns: int | None = None
    messages: int | None = None

    def text(self) -> str:
        """One line: ``chunk at byte 3754 (/joint/state, /plate/transform; 2026-11-18
        12:00:01.000–12:00:01.950 UTC; 41 messages): CRC mismatch``."""
        parts = [", ".join(self.topics) if self.topics else "topics unknown"]
        span = span_text(self.start_ns, self.end_ns)
        if span:
            parts.append(span)
        if self.messages is not None:
            parts.append(f"{self.messages} message(s)")
        return f"{self.record} at byte {self.offset} ({'; '.join(parts)}): {self.what}"

    def as_json(self) -> dict[str, Any]:
        """The item as a JSON object (``loopcal info --json``, ``loopcal verify --json``)."""
        return {
            "offset": self.offset, "length": self.length, "record": self.record,
            "what": self.what, "topics": list(self.topics) or None,
            "start_utc": _iso(self.start_ns), "end_utc": _iso(self.end_ns),
            "start_ns": self.start_ns, "end_ns": self.end_ns, "messages": self.messages,
        }  # fmt: skip


@dataclass
class Verification:
    """What checking every record of one file found.

    Attributes
    ----------
    path : pathlib.Path
        The file.
    size : int
        Its bytes.
    closed : bool
        It has a data end record or a footer (it was closed; damage may have hit either).
    records : int
        Records checked (inside chunks included).
    chunks : int
        Chunk records found in the data section.
    messages : dict of str to int
        Messages per topic in the chunks that checked out.
    damaged : list of Damaged
        What did not check out, by offset; empty when every record did.
    """

    path: Path
    size: int
    closed: bool = False
    records: int = 0
    chunks: int = 0
    messages: dict[str, int] = field(default_factory=dict)
    damaged: list[Damaged] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """Whether every record checked out."""
        return not self.damaged

    def as_json(self) -> dict[str, Any]:
        return {
            "path": str(self.path), "bytes": self.size, "closed": self.closed,
            "records": self.records, "chunks": self.chunks,
            "messages": dict(sorted(self.messages.items())),
            "damaged": [d.as_json() for d in self.damaged],
        }  # fmt: skip


# ---------------------------------------------------------------------------- records


@dataclass(slots=True)
class _ChunkIndex:
    """A chunk index record of the summary, and where it lies."""

    at: int
    length: int
    start_ns: int
    end_ns: int
    chunk_offset: int
    chunk_length: int
    index_offsets: dict[int, int]
    index_length: int
    compression: str
    compressed_size: int
    uncompressed_size: int


def _chunk_index(at: int, length: int, body: memoryview) -> _ChunkIndex:
    """A chunk index record's body with every length checked; ValueError if the fields do
    not fill it exactly."""
    n = len(body)
    if n < _INDEX_FIXED.size + 8 + 4 + 16:
        raise ValueError("short chunk index")
    start, end, offset, clen, map_len = _INDEX_FIXED.unpack_from(body, 0)
    pos = _INDEX_FIXED.size
    if map_len % _INDEX_ENTRY.size or pos + map_len + 12 > n:
        raise ValueError("chunk index map overruns the record")
    entries = list(_INDEX_ENTRY.iter_unpack(body[pos : pos + map_len]))
    offsets = dict(entries)
    if len(offsets) != len(entries):
        raise ValueError("a channel twice in the chunk index's map")
    pos += map_len
    (index_len,) = _U64.unpack_from(body, pos)
    (slen,) = _U32.unpack_from(body, pos + 8)
    pos += 12
    if pos + slen + 16 != n:
        raise ValueError("chunk index fields do not fill the record")
    compression = bytes(body[pos : pos + slen]).decode("utf-8")
    csize, usize = struct.unpack_from("<QQ", body, pos + slen)
    return _ChunkIndex(at, length, start, end, offset, clen, offsets, index_len, compression,
                       csize, usize)  # fmt: skip


@dataclass(slots=True)
class _MessageIndex:
    """A message index record after a chunk: its channel and (log time, offset) entries."""

    at: int
    length: int
    channel: int | None = None  # None: the record did not parse
    count: int = 0
    body: bytes = b""  # the entries, 16 bytes each

    @property
    def entries(self) -> np.ndarray:
        """(count, 2) uint64: log time, offset in the chunk."""
        return np.frombuffer(self.body, dtype="<u8").reshape(-1, 2)

    def pairs(self) -> list[tuple[int, int]]:
        """The entries as (log time, offset), by offset."""
        return sorted(_PAIR.iter_unpack(self.body), key=lambda e: e[1])


_PAIR = struct.Struct("<QQ")


def _message_index(at: int, length: int, body: memoryview) -> _MessageIndex:
    if len(body) < 6:
        return _MessageIndex(at, length)
    cid, nbytes = struct.unpack_from("<HI", body, 0)
    if nbytes % 16 or 6 + nbytes != len(body):
        return _MessageIndex(at, length)
    return _MessageIndex(at, length, cid, nbytes // 16, bytes(body[6:]))


@dataclass(slots=True)
class _Chunk:
    """A chunk record of the data section, what it held and the message indexes after it."""

    at: int
    length: int  # the whole record, head included
    start_ns: int | None = None
    end_ns: int | None = None
    compression: str = ""
    compressed_size: int = 0
    uncompressed_size: int = 0
    problem: str = ""  # "" if it checked out
    counts: dict[int, int] = field(default_factory=dict)  # channel id -> messages (intact)
    indexes: list[_MessageIndex] = field(default_factory=list)
    cut_index: bool = False  # a message index after it was cut off (named on its own)
    raw: bytes | None = None  # its records, decompressed and CRC-checked, until finished
    # (offset, channel id, log time) of its messages, until its indexes are checked
    found: list[tuple[int, int, int]] = field(default_factory=list)

    @property
    def end(self) -> int:
        return self.at + self.length

    @property
    def index_end(self) -> int:
        return self.indexes[-1].at + self.indexes[-1].length if self.indexes else self.end


_ZSTD = zstandard.ZstdDecompressor()


def _decompress(compression: str, data: memoryview, size: int) -> bytes:
    if compression == "":
        out = bytes(data)
    elif compression == "zstd":
        params = zstandard.get_frame_parameters(data)
        if params.content_size not in (size, zstandard.CONTENTSIZE_UNKNOWN):
            raise ValueError("zstd frame size differs from the chunk's")
        out = _ZSTD.decompress(data, max_output_size=size)
    else:
        import lz4.frame  # optional: only files written by other tools use it

        out = lz4.frame.decompress(bytes(data))
    if len(out) != size:
        raise ValueError("decompressed size differs from the chunk's")
    return out


# ---------------------------------------------------------------------------- the walk


class _Verifier:
    """One pass over a mapped file; :func:`verify_file` runs it."""

    def __init__(self, path: Path, mm: mmap.mmap, buf: memoryview) -> None:
        self.path, self.mm, self.buf, self.n = path, mm, buf, len(buf)
        self.out = Verification(path, self.n)
        self.strict = True
        self.header: Header | None = None
        self.footer: Footer | None = None
        self.footer_at = self.n - 8 - _FOOTER_BYTES
        self.chunks: list[_Chunk] = []
        self.metadata: dict[int, tuple[int, str, dict[str, str]]] = {}  # offset -> (len, name, map)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.data_end_at: int | None = None
        # the summary as parsed (trusted or not: what it says serves to name damage)
        self.summary_ok = False
        self.s_schemas: dict[int, Schema] = {}
        self.s_channels: dict[int, Channel] = {}
        self.s_chunk_indexes: list[_ChunkIndex] = []
        self.s_metadata_indexes: list[tuple[int, int, Any]] = []
        self.s_statistics: tuple[int, int, Statistics] | None = None
        self.s_offsets: list[tuple[int, int, Any]] = []
        self.s_groups: dict[int, list[tuple[int, int]]] = {}  # opcode -> [(at, length)]
        self.s_parsed_to: int | None = None  # where summary parsing stopped (None: the end)
        self.damaged: list[Damaged] = []
        self.batch: list[tuple[_Chunk, bytes]] = []  # intact chunks waiting for check_batch
        self.batch_bytes = 0
        self._by_offset: list[_ChunkIndex] | None = None
        self._offsets: list[int] = []
        self.unreadable = False  # a stretch of the data section held no readable record
        self.cut_topics: tuple[str, ...] = ()  # of a message index cut off after its chunk

    # -------------------------------------------------------------- helpers

    def damage(self, at: int, length: int, record: str, what: str, **kw: Any) -> None:
        self.damaged.append(Damaged(at, length, record, what, **kw))

    def topics_of(self, ids: Any) -> tuple[str, ...]:
        names = set()
        for cid in ids:
            ch = self.channels.get(cid) or self.s_channels.get(cid)
            if ch is not None:
                names.add(ch.topic)
            elif self.strict and cid in _OUR_TOPICS:
                names.add(_OUR_TOPICS[cid])
            else:
                names.add(f"channel {cid}")
        return tuple(sorted(names))

    def index_for(self, at: int, end: int) -> _ChunkIndex | None:
        """The summary's chunk index entry whose chunk overlaps [at, end), if any."""
        if self._by_offset is None:
            self._by_offset = sorted(self.s_chunk_indexes, key=lambda c: c.chunk_offset)
            self._offsets = [c.chunk_offset for c in self._by_offset]
        k = bisect.bisect_right(self._offsets, at) - 1
        for ci in self._by_offset[max(k, 0) : k + 2]:
            if ci.chunk_offset < end and at < ci.chunk_offset + ci.chunk_length:
                return ci
        k = bisect.bisect_left(self._offsets, at)
        if k < len(self._offsets) and self._offsets[k] < end:
            return self._by_offset[k]
        return None

    # -------------------------------------------------------------- the run

    def run(self) -> Verification:
        if self.n < 8 and MAGIC.startswith(bytes(self.buf)):
            return self.out  # created, nothing written (or nothing made durable)
        library = _library(self.buf)
        # ours (checked strictly: our writer always writes CRCs and indexes): the header names
        # loopcal, or is not intact
        self.strict = library.startswith("loopcal") or not library
        self.read_footer_and_summary()
        self.walk_data()
        if self.footer is not None or self.data_end_at is not None:
            self.out.closed = True
            self.check_summary()
        self.check_header_against_metadata()
        counts: Counter = Counter()
        for c in self.chunks:
            if not c.problem:
                counts.update(c.counts)
        self.out.messages = {self.topics_of([cid])[0]: k for cid, k in counts.items()}
        self.out.chunks = len(self.chunks)
        self.out.damaged = sorted(self.damaged, key=lambda d: (d.offset, d.record))
        return self.out

    # -------------------------------------------------------------- footer, summary

    def read_footer_and_summary(self) -> None:
        buf, n = self.buf, self.n
        if n < 8 + _FOOTER_BYTES + 8 or bytes(buf[n - 8 :]) != MAGIC:
            return
        at = record_at(buf, self.footer_at, n - 8)
        if at is None or at != (Opcode.FOOTER, 20):
            return
        self.out.records += 1
        try:
            footer: Footer = parse_record(Opcode.FOOTER, buf[self.footer_at + RECORD_HEAD : n - 8])
        except PARSE_ERRORS:
            return
        self.footer = footer
        if footer.summary_start == 0:
            if self.strict:
                self.damage(self.footer_at, _FOOTER_BYTES, "footer", "no summary section")
            return
        if not 8 <= footer.summary_start <= self.footer_at or not (
            footer.summary_offset_start == 0
            or footer.summary_start <= footer.summary_offset_start <= self.footer_at
        ):
            self.damage(self.footer_at, _FOOTER_BYTES, "footer",
                        f"points outside the file (summary at byte {footer.summary_start}, "
                        f"summary offsets at byte {footer.summary_offset_start})")  # fmt: skip
            self.footer = None
            return
        start = footer.summary_start
        crc = 0
        for p in range(start, self.footer_at + RECORD_HEAD + 16, _CRC_PIECE):
            crc = zlib.crc32(buf[p : min(p + _CRC_PIECE, self.footer_at + RECORD_HEAD + 16)], crc)
        if footer.summary_crc == 0:
            if self.strict:
                self.damage(start, self.footer_at - start, "summary", "summary without CRC")
        elif crc != footer.summary_crc:
            self.damage(start, self.footer_at - start, "summary", "summary CRC mismatch")
        else:
            self.summary_ok = True
        pos = start
        while pos < self.footer_at:
            at = record_at(buf, pos, self.footer_at)
            if at is None or at[0] not in _SUMMARY_OPCODES:
                what = ("record overruns the summary" if at is None else
                        f"{_name(at[0])} record in the summary section")  # fmt: skip
                self.damage(pos, self.footer_at - pos, "summary", what)
                self.s_parsed_to = pos
                return
            op, length = at
            self.out.records += 1
            body = buf[pos + RECORD_HEAD : pos + RECORD_HEAD + length]
            whole = RECORD_HEAD + length
            try:
                if op == Opcode.CHUNK_INDEX:
                    self.s_chunk_indexes.append(_chunk_index(pos, whole, body))
                else:
                    rec = parse_record(op, body)
                    if op == Opcode.SCHEMA:
                        self.s_schemas[rec.id] = rec
                    elif op == Opcode.CHANNEL:
                        self.s_channels[rec.id] = rec
                    elif op == Opcode.METADATA_INDEX:
                        self.s_metadata_indexes.append((pos, whole, rec))
                    elif op == Opcode.STATISTICS:
                        if self.s_statistics is not None:
                            self.damage(pos, whole, "statistics", "a second statistics record")
                        self.s_statistics = (pos, whole, rec)
                    elif op == Opcode.SUMMARY_OFFSET:
                        self.s_offsets.append((pos, whole, rec))
            except PARSE_ERRORS:
                self.damage(pos, whole, _name(op), "its fields do not fit the record")
            self.s_groups.setdefault(op, []).append((pos, whole))
            pos += whole

    # -------------------------------------------------------------- data section

    def walk_data(self) -> None:
        buf, n = self.buf, self.n
        limit = n
        if self.footer is not None and self.footer.summary_start:
            limit = self.footer.summary_start
        elif self.footer is not None:
            limit = self.footer_at
        if bytes(buf[:8]) != MAGIC:
            self.damage(0, 8, "header", "no MCAP magic at the start")
        pos = 8
        first = True
        chunk: _Chunk | None = None  # the chunk whose message indexes may follow
        while pos < limit:
            at = record_at(buf, pos, limit)
            op = buf[pos]
            if at is None or not (0x01 <= op <= 0x0F or op >= 0x80):
                if chunk is not None:
                    # an index of it cut off: its messages' index is not missing, it is cut
                    chunk.cut_index = op == Opcode.MESSAGE_INDEX
                    self.finish_chunk(chunk)
                    chunk = None
                pos, chunk = self.bad_bytes(pos, limit, cut=at is None and 0x01 <= op <= 0x0F)
                if chunk is not None:
                    self.chunks.append(chunk)
                first = False
                continue
            op, length = at
            whole = RECORD_HEAD + length
            body = buf[pos + RECORD_HEAD : pos + whole]
            self.out.records += 1
            if op != Opcode.MESSAGE_INDEX and chunk is not None:
                self.finish_chunk(chunk)
                chunk = None
            if first and op != Opcode.HEADER:
                self.damage(8, 0, "header", f"no header record (found a {_name(op)} record)")
            if op == Opcode.HEADER:
                if not first:
                    self.damage(pos, whole, "header", "a second header record")
                else:
                    try:
                        self.header = parse_record(op, body)
                    except PARSE_ERRORS:
                        self.damage(pos, whole, "header", "its fields do not fit the record")
            elif op == Opcode.CHUNK:
                chunk = self.check_chunk(pos, whole, body)
                self.chunks.append(chunk)
            elif op == Opcode.MESSAGE_INDEX:
                mi = _message_index(pos, whole, body)
                if chunk is None:
                    self.damage(
                        pos,
                        whole,
                        "message index",
                        "not after a chunk",
                        topics=() if mi.channel is None else self.topics_of([mi.channel]),
                    )
                else:
                    chunk.indexes.append(mi)
            elif op == Opcode.METADATA:
                try:
                    rec = parse_record(op, body)
                    self.metadata[pos] = (whole, rec.name, dict(rec.metadata))
                except PARSE_ERRORS:
                    self.damage(pos, whole, "metadata", "its fields do not fit the record")
            elif op in (Opcode.SCHEMA, Opcode.CHANNEL):
                try:
                    rec = parse_record(op, body)
                    (self.schemas if op == Opcode.SCHEMA else self.channels)[rec.id] = rec
                except PARSE_ERRORS:
                    self.damage(pos, whole, _name(op), "its fields do not fit the record")
            elif op == Opcode.DATA_END:
                self.check_data_end(pos, whole, body)
                pos += whole
                break
            elif op in (Opcode.FOOTER, *_SUMMARY_OPCODES - {Opcode.SCHEMA, Opcode.CHANNEL}):
                self.damage(pos, whole, _name(op), "a summary record in the data section")
            elif op in (Opcode.ATTACHMENT, Opcode.MESSAGE) or op >= 0x80:
                if self.strict:  # our writer writes neither, nor private records
                    self.damage(pos, whole, _name(op), "a record our writer never writes here")
            first = False
            pos += whole
        if chunk is not None:
            self.finish_chunk(chunk)
        self.check_batch()
        if self.footer is not None:
            if self.data_end_at is None:
                self.damage(min(pos, limit), 0, "data end", "no data end record before the "
                            "summary")  # fmt: skip
            elif pos != limit:
                self.damage(pos, limit - pos, "records",
                            "bytes between the data end record and the summary")  # fmt: skip
        elif self.data_end_at is not None:
            self.damage(pos, n - pos, "footer", "no intact footer after the data end record "
                        "(the file was closed, its end is damaged)")  # fmt: skip

    def check_data_end(self, pos: int, whole: int, body: memoryview) -> None:
        self.data_end_at = pos
        try:
            rec = parse_record(Opcode.DATA_END, body)
        except PARSE_ERRORS:
            self.damage(pos, whole, "data end", "its fields do not fit the record")
            return
        if whole != _DATA_END_BYTES:
            self.damage(pos, whole, "data end", f"{whole} bytes, not {_DATA_END_BYTES}")
        if rec.data_section_crc:
            crc = 0
            for p in range(0, pos, _CRC_PIECE):
                crc = zlib.crc32(self.buf[p : min(p + _CRC_PIECE, pos)], crc)
            # damage already named in the data section explains a mismatch; alone, it is
            # damage no other check sees (the header, a metadata value)
            if crc != rec.data_section_crc and not any(d.offset < pos for d in self.damaged):
                self.damage(0, pos, "data section", "data section CRC mismatch (the header or "
                            "a metadata record changed: no other check covers them)")

    def bad_bytes(self, pos: int, limit: int, *, cut: bool) -> tuple[int, _Chunk | None]:
        """Name the stretch from ``pos`` where no record can be read; returns where to go on
        (the next chunk that checks out, or the data end a footer gives, or ``limit``) and,
        where the summary's chunk index says a chunk lay exactly there and a record starts
        right after it, that chunk (damaged), whose message indexes then follow."""
        buf = self.buf
        ci = self.index_for(pos, pos + 1)
        if ci is not None and ci.chunk_offset != pos:
            ci = None
        after = ci.chunk_offset + ci.chunk_length if ci is not None else None
        if after is not None and not (
            pos < after < limit
            and (at := record_at(buf, after, limit)) is not None
            and at[0] in (Opcode.MESSAGE_INDEX, Opcode.CHUNK, Opcode.DATA_END)
        ):
            after = None
        nxt = after if after is not None else self.resync(pos + 1, limit)
        end = limit if nxt is None else nxt
        if ci is None:
            ci = self.index_for(pos, end)
        topics: tuple[str, ...] = ()
        start_ns = end_ns = None
        if ci is not None:
            topics, start_ns, end_ns = self.topics_of(ci.index_offsets), ci.start_ns, ci.end_ns
        elif buf[pos] == Opcode.CHUNK and pos + RECORD_HEAD + 16 <= self.n:
            s, e = struct.unpack_from("<QQ", buf, pos + RECORD_HEAD)
            if s <= e:
                start_ns, end_ns = s, e
        if nxt is None and cut and self.footer is None:
            what = "cut off: the last record is incomplete"
        elif not any(buf[pos : min(pos + RECORD_HEAD, self.n)]):
            what = "zeros where records should be (a torn write or power loss)"
        elif buf[pos] == Opcode.CHUNK:
            what = "a chunk whose length overruns the data section"
        else:
            what = "no valid record"
        if after is not None:
            return end, _Chunk(pos, end - pos, start_ns, end_ns, problem=what)
        record = "chunk" if buf[pos] == Opcode.CHUNK or ci is not None else "records"
        if record == "records" and cut and nxt is None:
            record = _name(buf[pos])
            if buf[pos] == Opcode.MESSAGE_INDEX:
                topics = self.cut_topics
        self.unreadable = True
        self.damage(pos, end - pos, record, what, topics=topics, start_ns=start_ns,
                    end_ns=end_ns)  # fmt: skip
        return end, None

    def resync(self, lo: int, limit: int) -> int | None:
        """The first offset at or after ``lo`` where a chunk that checks out starts, or the
        data end record's (as the footer gives it); None if neither."""
        data_end = None
        if self.footer is not None and self.footer.summary_start >= lo + _DATA_END_BYTES:
            data_end = self.footer.summary_start - _DATA_END_BYTES
        for ci in sorted(self.s_chunk_indexes, key=lambda c: c.chunk_offset):
            if ci.chunk_offset >= lo and self.chunk_checks_out(ci.chunk_offset, limit):
                if data_end is None or ci.chunk_offset < data_end:
                    return ci.chunk_offset
        p = lo
        stop = data_end if data_end is not None else limit
        while True:
            p = self.mm.find(b"\x06", p, stop)
            if p < 0:
                return data_end
            if self.chunk_checks_out(p, limit):
                return p
            p += 1

    def chunk_checks_out(self, p: int, limit: int) -> bool:
        at = record_at(self.buf, p, limit)
        if at is None or at[0] != Opcode.CHUNK:
            return False
        body = self.buf[p + RECORD_HEAD : p + RECORD_HEAD + at[1]]
        head = chunk_header(body)
        if head is None or head[2] > MAX_CHUNK_BYTES:
            return False
        start, end, usize, crc, compression, data = head
        try:
            raw = _decompress(compression, data, usize)
        except (ImportError, *PARSE_ERRORS):
            return False
        return zlib.crc32(raw) == crc and (crc != 0 or not self.strict)

    # -------------------------------------------------------------- chunks

    def check_chunk(self, pos: int, whole: int, body: memoryview) -> _Chunk:
        c = _Chunk(pos, whole)
        head = chunk_header(body)
        if head is None:
            c.problem = "damaged chunk header (its fields do not fit the record)"
            if len(body) >= 16:
                s, e = struct.unpack_from("<QQ", body, 0)
                if s <= e:
                    c.start_ns, c.end_ns = s, e
            return c
        start, end, usize, crc, compression, data = head
        c.start_ns, c.end_ns, c.uncompressed_size = start, end, usize
        c.compression, c.compressed_size = compression, len(data)
        if crc == 0 and self.strict:
            c.problem = "no CRC written (our writer always writes one)"
            return c
        if usize > MAX_CHUNK_BYTES:
            c.problem = f"claims {usize} bytes uncompressed"
            return c
        try:
            raw = _decompress(compression, data, usize)
        except (ImportError, *PARSE_ERRORS):
            c.problem = "does not decompress"
            return c
        if crc != 0 and zlib.crc32(raw) != crc:
            c.problem = "CRC mismatch"
            return c
        c.raw = raw  # its records are checked with its message indexes (finish_chunk)
        return c

    def indexed(self, c: _Chunk, raw: bytes) -> bool:
        """Queue an intact chunk whose message indexes all parse, one per channel, for
        :meth:`check_batch`; False if they do not (it is then checked record by record)."""
        idx = c.indexes
        if c.cut_index or not idx or any(mi.channel is None or not mi.count for mi in idx) or \
                len({mi.channel for mi in idx}) != len(idx):  # fmt: skip
            return False
        self.batch.append((c, raw))
        self.batch_bytes += len(raw)
        if self.batch_bytes >= _BATCH_BYTES:
            self.check_batch()
        return True

    def check_batch(self) -> None:
        """Check the queued chunks' records through their message indexes, all at once with
        numpy: every entry must point at a message record of its channel and log time, and
        those records, with the others (schemas, channels) walked one by one, must fill each
        chunk exactly, record after record, its messages' log times spanning its header's. If
        anything does not, each chunk of the batch is checked record by record instead
        (:meth:`chunk_records`), which says what is wrong and where."""
        batch, self.batch, self.batch_bytes = self.batch, [], 0
        if batch and not self.batch_checks_out(batch):
            for c, raw in batch:
                c.problem = self.chunk_records(c, raw)
                self.finish_records(c)

    def batch_checks_out(self, batch: list[tuple[_Chunk, bytes]]) -> bool:
        raw = b"".join(r for _, r in batch)
        sizes = np.array([len(r) for _, r in batch], dtype=np.int64)
        bases = np.concatenate(([0], np.cumsum(sizes)[:-1]))
        indexes = [(k, mi) for k, (c, _) in enumerate(batch) for mi in c.indexes]
        counts = [mi.count for _, mi in indexes]
        entries = np.frombuffer(b"".join(mi.body for _, mi in indexes), dtype="<u8")
        entries = entries.reshape(-1, 2)
        chunk = np.repeat(np.array([k for k, _ in indexes], dtype=np.int64), counts)
        cids = np.repeat(np.array([mi.channel for _, mi in indexes], dtype=np.uint64), counts)
        offs = entries[:, 1].astype(np.int64)
        if (entries[:, 1] > np.uint64(MAX_CHUNK_BYTES)).any() or (
            offs + RECORD_HEAD + _MESSAGE_FIXED.size > sizes[chunk]
        ).any():
            return False
        offs += bases[chunk]
        order = np.argsort(offs, kind="stable")
        offs, chunk = offs[order], chunk[order]
        logs, cids = entries[order, 0], cids[order]
        a = np.frombuffer(raw, dtype=np.uint8)
        if (a[offs] != Opcode.MESSAGE).any():
            return False
        lens = _gather(a, offs + 1, "<u8")
        if (lens < _MESSAGE_FIXED.size).any() or (lens > np.uint64(MAX_CHUNK_BYTES)).any():
            return False
        ends = offs + RECORD_HEAD + lens.astype(np.int64)
        limits = bases + sizes
        if (ends > limits[chunk]).any() or (ends[:-1] > offs[1:]).any():
            return False
        if (_gather(a, offs + RECORD_HEAD, "<u2") != cids).any():
            return False
        if (_gather(a, offs + RECORD_HEAD + 6, "<u8") != logs).any():
            return False
        firsts = np.flatnonzero(np.diff(chunk, prepend=-1))
        if len(firsts) != len(batch):
            return False
        lasts = np.append(firsts[1:], len(offs)) - 1
        spans = np.column_stack((np.minimum.reduceat(logs, firsts),
                                 np.maximum.reduceat(logs, firsts)))  # fmt: skip
        want = np.array([(c.start_ns, c.end_ns) for c, _ in batch], dtype=np.uint64)
        if not np.array_equal(spans, want):
            return False
        # what lies between the messages: schemas and channels only, filling it exactly
        gaps = np.flatnonzero((ends[:-1] != offs[1:]) & (chunk[:-1] == chunk[1:]))
        between = [(int(ends[i]), int(offs[i + 1])) for i in gaps]
        between += [(int(bases[k]), int(offs[f])) for k, f in enumerate(firsts)
                    if offs[f] != bases[k]]  # fmt: skip
        between += [(int(ends[e]), int(limits[k])) for k, e in enumerate(lasts)
                    if ends[e] != limits[k]]  # fmt: skip
        records = len(offs)
        for lo, hi in sorted(between):
            got = self.other_records(raw, lo, hi)
            if got is None:
                return False
            records += got
        if any(mi.channel not in self.channels for c, _ in batch for mi in c.indexes) and \
                not any(x.problem for x in self.chunks):  # fmt: skip
            return False
        self.out.records += records
        for c, _ in batch:
            c.counts = {mi.channel: mi.count for mi in c.indexes}
            for mi in c.indexes:
                mi.body = b""  # checked: its channel, place and count are what is kept
        return True

    def other_records(self, raw: bytes, lo: int, hi: int) -> int | None:
        """The schema and channel records filling raw[lo:hi] exactly (taken in), or None."""
        p, k = lo, 0
        while p < hi:
            if p + RECORD_HEAD > hi:
                return None
            op, rlen = _HEAD.unpack_from(raw, p)
            b = p + RECORD_HEAD
            if op not in (Opcode.SCHEMA, Opcode.CHANNEL) or b + rlen > hi:
                return None
            try:
                rec = parse_record(op, memoryview(raw)[b : b + rlen])
            except PARSE_ERRORS:
                return None
            if op == Opcode.SCHEMA:
                self.schemas.setdefault(rec.id, rec)
            else:
                if rec.schema_id and rec.schema_id not in self.schemas:
                    return None
                self.channels.setdefault(rec.id, rec)
            p, k = b + rlen, k + 1
        return k

    def chunk_records(self, c: _Chunk, raw: bytes) -> str:
        """Check the records inside an intact chunk one by one, keeping its messages' (offset,
        channel, log time) in ``c.found``; "" or what is wrong."""
        n, p = len(raw), 0
        unpack = _MESSAGE_HEAD.unpack_from
        found = c.found
        add = found.append
        records = 0
        try:
            while p < n:
                if p + _MESSAGE_HEAD.size <= n:
                    op, rlen, cid, _seq, log, _pub = unpack(raw, p)
                else:
                    op, rlen = _HEAD.unpack_from(raw, p)
                records += 1
                if op == Opcode.MESSAGE:
                    if rlen < _MESSAGE_FIXED.size or p + _MESSAGE_HEAD.size > n:
                        return "a short message record inside"
                    add((p, cid, log))
                elif op in (Opcode.SCHEMA, Opcode.CHANNEL):
                    if self.other_records(raw, p, min(n, p + RECORD_HEAD + rlen)) != 1:
                        return f"a damaged {_name(op)} record inside"
                else:
                    return f"a {_name(op)} record inside"
                p += RECORD_HEAD + rlen
        except struct.error:
            return "its records overrun the chunk"
        if p != n:
            return "its records overrun the chunk"
        self.out.records += records
        if found:
            lo, hi = min(f[2] for f in found), max(f[2] for f in found)
            if (lo, hi) != (c.start_ns, c.end_ns):
                return (f"its header's time span ({c.start_ns}–{c.end_ns} ns) is not its "
                        f"messages' ({lo}–{hi} ns)")  # fmt: skip
        elif (c.start_ns or c.end_ns) and self.strict:
            return "no messages, yet its header gives a time span"
        c.counts = Counter(f[1] for f in found)
        unknown = [cid for cid in c.counts if cid not in self.channels]
        if unknown and not any(x.problem for x in self.chunks):
            return f"messages on channel {unknown[0]}, which no channel record defines"
        return ""

    def finish_chunk(self, c: _Chunk) -> None:
        """The chunk is complete with its message indexes: check them, and name it if it is
        damaged (its topics and time span from the indexes that describe it)."""
        raw, c.raw = c.raw, None
        if raw is not None and self.indexed(c, raw):
            return  # checked with its batch
        self.check_batch()  # the chunks before it first (their channels, schemas)
        if raw is not None:
            c.problem = self.chunk_records(c, raw)
        self.finish_records(c)

    def finish_records(self, c: _Chunk) -> None:
        """Check the message indexes of a chunk walked record by record against what it
        held, and name the chunk if it is damaged."""
        found, c.found = c.found, []
        seen: set[int] = set()
        for mi in c.indexes:
            topics = () if mi.channel is None else self.topics_of([mi.channel])
            kw = dict(topics=topics, start_ns=c.start_ns, end_ns=c.end_ns)
            if mi.channel is None:
                self.damage(mi.at, mi.length, "message index",
                            f"its fields do not fit the record (after the chunk at byte {c.at})",
                            topics=self.chunk_topics(c), start_ns=c.start_ns,
                            end_ns=c.end_ns)  # fmt: skip
                continue
            if mi.channel in seen:
                self.damage(mi.at, mi.length, "message index",
                            f"a second index of channel {mi.channel} after the chunk at byte "
                            f"{c.at}", messages=mi.count, **kw)  # fmt: skip
                continue
            seen.add(mi.channel)
            if c.problem:
                continue  # what the chunk held is unknown: the index cannot be checked
            want = [(log, off) for off, cid, log in found if cid == mi.channel]
            got = mi.pairs()
            if got != want:
                self.damage(mi.at, mi.length, "message index",
                            _index_difference(got, want, c.at), messages=mi.count,
                            **kw)  # fmt: skip
        if not c.problem and c.indexes:
            missing = sorted(set(c.counts) - seen)
            if missing and c.cut_index:
                self.cut_topics = self.topics_of(missing)
            elif missing:
                self.damage(c.at, c.length, "chunk",
                            f"no message index for its messages on channel(s) "
                            f"{', '.join(map(str, missing))}", topics=self.topics_of(missing),
                            start_ns=c.start_ns, end_ns=c.end_ns,
                            messages=sum(c.counts[m] for m in missing))  # fmt: skip
        elif not c.problem and found and self.strict:
            self.damage(c.at, c.length, "chunk", "no message index after it",
                        topics=self.topics_of(c.counts), start_ns=c.start_ns, end_ns=c.end_ns,
                        messages=sum(c.counts.values()))  # fmt: skip
        if c.problem:
            indexed = [mi for mi in c.indexes if mi.channel is not None]
            messages = sum(mi.count for mi in indexed) if indexed else None
            ci = self.index_for(c.at, c.end)
            if messages is None and ci is not None and not ci.index_offsets:
                messages = 0
            self.damage(c.at, c.length, "chunk", c.problem, topics=self.chunk_topics(c),
                        start_ns=c.start_ns, end_ns=c.end_ns, messages=messages)  # fmt: skip
            if indexed:  # what the damaged chunk held, by its indexes (for the statistics)
                c.counts = Counter({mi.channel: mi.count for mi in indexed})
        for mi in c.indexes:
            mi.body = b""  # checked: its channel, place and count are what is kept

    def chunk_topics(self, c: _Chunk) -> tuple[str, ...]:
        """The topics of a chunk whose content cannot be trusted: its chunk index entry's
        channels, else its message indexes', else its own messages' (if it decompressed), else
        none."""
        ci = self.index_for(c.at, c.end)
        if ci is not None and ci.chunk_offset == c.at and ci.index_offsets:
            return self.topics_of(ci.index_offsets)
        ids = [mi.channel for mi in c.indexes if mi.channel is not None]
        if ids:
            return self.topics_of(ids)
        return ()

    # -------------------------------------------------------------- summary against data

    def check_summary(self) -> None:
        if self.footer is None or not self.footer.summary_start:
            return  # no summary to check (its absence is named)
        footer = self.footer
        if self.data_end_at is not None and footer.summary_start != self.data_end_at + \
                _DATA_END_BYTES:  # fmt: skip
            self.damage(self.footer_at, _FOOTER_BYTES, "footer",
                        f"summary start {footer.summary_start} is not where the data end "
                        f"record ends ({self.data_end_at + _DATA_END_BYTES})")  # fmt: skip
        offsets_group = self.s_groups.get(Opcode.SUMMARY_OFFSET, [])
        want_offsets = offsets_group[0][0] if offsets_group else 0
        if self.s_parsed_to is None and footer.summary_offset_start != want_offsets:
            self.damage(self.footer_at, _FOOTER_BYTES, "footer",
                        f"summary offsets start at byte {want_offsets}, the footer says "
                        f"{footer.summary_offset_start}")  # fmt: skip
        self.check_schemas_and_channels()
        self.check_chunk_indexes()
        self.check_metadata_indexes()
        self.check_summary_offsets()
        self.check_statistics()

    def check_schemas_and_channels(self) -> None:
        for group, ours, theirs in ((Opcode.SCHEMA, self.schemas, self.s_schemas),
                                    (Opcode.CHANNEL, self.channels, self.s_channels)):  # fmt: skip
            places = dict(zip(theirs, self.s_groups.get(group, []), strict=False))
            for rid, rec in theirs.items():
                mine = ours.get(rid)
                if mine is not None and mine != rec:
                    at, length = places.get(rid, (self.footer.summary_start, 0))
                    topics = (rec.topic,) if group == Opcode.CHANNEL else ()
                    self.damage(at, length, _name(group),
                                f"{_name(group)} {rid} differs from the data section's",
                                topics=topics)  # fmt: skip
            if self.strict and self.s_parsed_to is None and not any(c.problem for c in self.chunks):
                for rid in set(ours) - set(theirs):
                    self.damage(
                        self.footer.summary_start,
                        0,
                        "summary",
                        f"{_name(group)} {rid} of the data section is not in the summary",
                    )

    def check_chunk_indexes(self) -> None:
        chunks = {c.at: c for c in self.chunks}
        by_order = len(self.s_chunk_indexes) == len(self.chunks)
        described: set[int] = set()
        for k, ci in enumerate(self.s_chunk_indexes):
            c = chunks.get(ci.chunk_offset)
            meant = c if c is not None else (self.chunks[k] if by_order else None)
            if c is None and self.in_unreadable(ci.chunk_offset):
                continue  # the stretch it points into is named damaged

            def described_by(ci: _ChunkIndex = ci, meant: _Chunk | None = meant) -> dict:
                """The topics and span of the chunk an entry describes: that chunk's own when
                it checked out, else the entry's."""
                if meant is not None and not meant.problem and meant.counts:
                    return dict(topics=self.topics_of(meant.counts), start_ns=meant.start_ns,
                                end_ns=meant.end_ns)  # fmt: skip
                return dict(topics=self.topics_of(ci.index_offsets), start_ns=ci.start_ns,
                            end_ns=ci.end_ns)  # fmt: skip

            if c is None:
                where = f" (the chunk at byte {meant.at}?)" if meant is not None else ""
                self.damage(ci.at, ci.length, "chunk index",
                            f"points to byte {ci.chunk_offset}, where no chunk starts{where}",
                            **described_by())  # fmt: skip
                continue
            described.add(c.at)
            if c.problem:
                continue  # the chunk is named damaged; its fields cannot be checked
            wrong = []
            if ci.chunk_length != c.length:
                wrong.append(f"chunk length {ci.chunk_length}, not {c.length}")
            if (ci.start_ns, ci.end_ns) != (c.start_ns, c.end_ns):
                wrong.append(f"time span {ci.start_ns}–{ci.end_ns} ns, not "
                             f"{c.start_ns}–{c.end_ns}")  # fmt: skip
            if ci.compression != c.compression:
                wrong.append(f"compression {ci.compression!r}, not {c.compression!r}")
            if ci.compressed_size != c.compressed_size:
                wrong.append(f"compressed size {ci.compressed_size}, not {c.compressed_size}")
            if ci.uncompressed_size != c.uncompressed_size:
                wrong.append(f"uncompressed size {ci.uncompressed_size}, not "
                             f"{c.uncompressed_size}")  # fmt: skip
            indexes = {mi.channel: mi.at for mi in c.indexes if mi.channel is not None}
            if ci.index_offsets != indexes:
                wrong.append(f"message index offsets {_mapping(ci.index_offsets)}, not "
                             f"{_mapping(indexes)}")  # fmt: skip
            if ci.index_length != c.index_end - c.end:
                wrong.append(f"message index length {ci.index_length}, not "
                             f"{c.index_end - c.end}")  # fmt: skip
            if wrong:
                self.damage(ci.at, ci.length, "chunk index",
                            f"for the chunk at byte {c.at}: " + "; ".join(wrong),
                            messages=sum(c.counts.values()), **described_by())  # fmt: skip
        if self.strict and self.s_parsed_to is None:
            for c in self.chunks:
                if c.at not in described and not c.problem:
                    self.damage(c.at, c.length, "chunk", "not in the summary's chunk index",
                                topics=self.topics_of(c.counts), start_ns=c.start_ns,
                                end_ns=c.end_ns, messages=sum(c.counts.values()))  # fmt: skip

    def in_unreadable(self, at: int) -> bool:
        return any(d.record in ("records", "chunk") and d.offset <= at < d.offset + d.length
                   for d in self.damaged)  # fmt: skip

    def check_metadata_indexes(self) -> None:
        indexed = set()
        for at, length, mi in self.s_metadata_indexes:
            got = self.metadata.get(mi.offset)
            if got is None:
                self.damage(at, length, "metadata index",
                            f"points to byte {mi.offset}, where no intact metadata record "
                            f"starts (name {mi.name!r})")  # fmt: skip
            elif (got[0], got[1]) != (mi.length, mi.name):
                self.damage(at, length, "metadata index",
                            f"says {mi.name!r} of {mi.length} bytes at byte {mi.offset}; the "
                            f"record there is {got[1]!r} of {got[0]} bytes")  # fmt: skip
            indexed.add(mi.offset)
        if self.strict and self.s_parsed_to is None:
            for at, (length, name, _) in self.metadata.items():
                if at not in indexed:
                    self.damage(at, length, "metadata", f"{name!r} is not in the summary's "
                                "metadata index")  # fmt: skip

    def check_summary_offsets(self) -> None:
        if self.s_parsed_to is not None:
            return
        named = set()
        for at, length, so in self.s_offsets:
            group = self.s_groups.get(so.group_opcode, [])
            start = group[0][0] if group else so.group_start
            size = sum(g[1] for g in group)
            contiguous = all(a + n == b for (a, n), (b, _) in zip(group, group[1:], strict=False))
            if so.group_opcode in named or (so.group_start, so.group_length) != (start, size) \
                    or not contiguous:  # fmt: skip
                self.damage(at, length, "summary offset",
                            f"the {_name(so.group_opcode)} group at byte {so.group_start} of "
                            f"{so.group_length} bytes; the summary's is at byte {start} of "
                            f"{size}")  # fmt: skip
            named.add(so.group_opcode)

    def check_statistics(self) -> None:
        if self.s_statistics is None:
            if self.strict and self.s_parsed_to is None:
                self.damage(self.footer.summary_start, 0, "summary", "no statistics record")
            return
        at, length, st = self.s_statistics
        if (
            any(c.problem and not c.counts for c in self.chunks)
            or self.unreadable
            or self.s_parsed_to is not None
        ):
            return  # what a damaged chunk held is unknown: the counts cannot be checked
        counts: Counter = Counter()
        for c in self.chunks:
            counts.update(c.counts)
        stats = Counter({k: v for k, v in st.channel_message_counts.items()})
        wrong, topics = [], set()
        diff = 0
        for cid in sorted(set(counts) | set(stats)):
            if counts[cid] != stats[cid]:
                t = self.topics_of([cid])[0]
                topics.add(t)
                diff += abs(counts[cid] - stats[cid])
                wrong.append(f"{t} {stats[cid]} message(s), found {counts[cid]}")
        total = sum(counts.values())
        if st.message_count != total:
            wrong.append(f"message count {st.message_count}, found {total}")
        if st.chunk_count != len(self.chunks):
            wrong.append(f"chunk count {st.chunk_count}, found {len(self.chunks)}")
        if st.metadata_count != len(self.metadata):
            wrong.append(f"metadata count {st.metadata_count}, found {len(self.metadata)}")
        if st.attachment_count != 0:
            wrong.append(f"attachment count {st.attachment_count}, found 0")
        schemas = set(self.schemas) | set(self.s_schemas)
        channels = set(self.channels) | set(self.s_channels)
        if st.schema_count != len(schemas):
            wrong.append(f"schema count {st.schema_count}, found {len(schemas)}")
        if st.channel_count != len(channels):
            wrong.append(f"channel count {st.channel_count}, found {len(channels)}")
        spans = [(c.start_ns, c.end_ns) for c in self.chunks if c.counts and c.start_ns is not None]
        if spans:
            lo, hi = min(s for s, _ in spans), max(e for _, e in spans)
            if (st.message_start_time, st.message_end_time) != (lo, hi):
                wrong.append(f"time span {st.message_start_time}–{st.message_end_time} ns, "
                             f"found {lo}–{hi}")  # fmt: skip
        if wrong:
            lo = st.message_start_time if st.message_count else None
            self.damage(at, length, "statistics", "; ".join(wrong), topics=tuple(sorted(topics)),
                        start_ns=lo, end_ns=st.message_end_time if lo is not None else None,
                        messages=diff or None)  # fmt: skip

    # -------------------------------------------------------------- header and metadata

    def check_header_against_metadata(self) -> None:
        own = [(at, v) for at, v in self.metadata.items() if v[1] == "loopcal"]
        if not own:
            return
        at, (length, _, values) = own[0]
        fmt = values.get("format")
        if fmt is not None and fmt not in READ_FORMATS:
            self.damage(at, length, "metadata", f"loopcal format {fmt!r}, not one of "
                        f"{', '.join(READ_FORMATS)}")  # fmt: skip
        version = values.get("version")
        if version and self.header is not None and self.header.library != f"loopcal {version}":
            self.damage(8, 0, "header", f"library {self.header.library!r}, while the loopcal "
                        f"metadata says version {version!r}")  # fmt: skip


def _library(buf: memoryview) -> str:
    """The header's library, or "" if the header is not intact (read before the walk)."""
    at = record_at(buf, 8, len(buf)) if bytes(buf[:8]) == MAGIC else None
    if at is None or at[0] != Opcode.HEADER:
        return ""
    try:
        return parse_record(Opcode.HEADER, buf[8 + RECORD_HEAD : 8 + RECORD_HEAD + at[1]]).library
    except PARSE_ERRORS:
        return ""


def _gather(a: np.ndarray, offsets: np.ndarray, dtype: str) -> np.ndarray:
    """The little-endian integers of ``dtype`` at byte ``offsets`` of the bytes ``a``."""
    width = np.dtype(dtype).itemsize
    return a[offsets[:, None] + np.arange(width)].view(dtype).ravel()


def _mapping(d: dict[int, int]) -> str:
    return "{" + ", ".join(f"{k}: {v}" for k, v in sorted(d.items())) + "}"


def _index_difference(
    got: list[tuple[int, int]], want: list[tuple[int, int]], chunk_at: int
) -> str:
    """How a message index's entries (by offset) differ from the chunk's messages."""
    where = f"the chunk at byte {chunk_at}"
    if len(got) != len(want):
        return f"{len(got)} entries, {where} holds {len(want)} message(s) of its channel"
    (glog, goff), (wlog, woff) = next((g, w) for g, w in zip(got, want, strict=True) if g != w)
    if goff != woff:
        return f"an entry points to byte {goff} of {where}, where no message of its channel is"
    return f"an entry gives log time {glog} for the message at byte {goff} of {where} ({wlog})"


def verify_file(path: str | os.PathLike) -> Verification:
    """Check every record of one recording file (see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    Verification
        What was checked and what did not check out.

    Raises
    ------
    RecordingError
        If the file cannot be opened or mapped.
    """
    p = Path(path)
    try:
        with open(p, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size == 0:
                return Verification(p, 0)
            mm = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError) as exc:
        raise RecordingError(f"{p}: cannot read: {getattr(exc, 'strerror', None) or exc}") \
            from None  # fmt: skip
    buf = memoryview(mm)
    try:
        return _Verifier(p, mm, buf).run()
    finally:
        buf.release()
        try:
            mm.close()
        except BufferError:  # a view still referenced: the mapping goes with it
            pass


__all__ = ["Damaged", "Verification", "span_text", "verify_file"]
