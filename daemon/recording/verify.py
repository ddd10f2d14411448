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

What does not check out is a :class:`~loopcal.daemon.recording.damage.Damage` item: its byte
offset and length, the record, what was wrong, the topics its messages were on (from the
chunk index's channel ids, the message indexes, or the chunk's own records; empty when
nothing says) and their time span.
A file not closed (no data end, no footer: a crash, or the file being written) is no damage
in itself; a last record cut off by the end of the file is.

MCAP gives metadata records and the header no CRC of their own: only the data section's
CRC (in the data end record) covers them. Files written since format 1's recorders turned
it on have one; in older files a flipped character in a metadata value that keeps the
record's shape reads as a different value. The header's library
is checked against the ``loopcal`` metadata's version and that record's format against the
format version; other metadata values are taken as they are.

The records are parsed by :mod:`~loopcal.daemon.recording.mcap_records`, the parser the reader
shares; the chunks and message indexes are checked by
:mod:`~loopcal.daemon.recording.verify_chunks`, the summary against the data section by
:mod:`~loopcal.daemon.recording.verify_summary`.
"""

from __future__ import annotations

import bisect
import mmap
import os
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Footer, Header, Schema, Statistics

from .damage import Damage
from .errors import RecordingError
from .mcap_records import (
    DATA_END_BYTES,
    FOOTER_BYTES,
    MAGIC,
    PARSE_ERRORS,
    RECORD_HEAD,
    chunk_checks_out,
    chunk_index,
    known_opcode,
    next_chunk,
    opcode_name,
    parse_record,
    read_header,
    record_at,
)
from .schemas import READ_FORMATS, format_words, our_topic
from .verify_chunks import ChunkAt, ChunkChecks, message_index_at
from .verify_summary import SummaryChecks

_CRC_PIECE = 1 << 24  # bytes given to zlib.crc32 at once over the mapped file
_SUMMARY_OPCODES = {Opcode.SCHEMA, Opcode.CHANNEL, Opcode.CHUNK_INDEX, Opcode.ATTACHMENT_INDEX,
                    Opcode.METADATA_INDEX, Opcode.STATISTICS, Opcode.SUMMARY_OFFSET}  # fmt: skip
#: verify's name for :class:`~loopcal.daemon.recording.damage.Damage` (one type for every
#: reader of damaged files)
Damaged = Damage


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
    damaged : list of Damage
        What did not check out, by offset; empty when every record did.
    chunk_spans : list of (int, int, tuple of str)
        Of each chunk that checked out: its first and last message log times, ns since the
        Unix epoch, and the topics of its messages (not in :meth:`as_json`).
    """

    path: Path
    size: int
    closed: bool = False
    records: int = 0
    chunks: int = 0
    messages: dict[str, int] = field(default_factory=dict)
    damaged: list[Damage] = field(default_factory=list)
    chunk_spans: list[tuple[int, int, tuple[str, ...]]] = field(default_factory=list)

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


# ---------------------------------------------------------------------------- the walk


class Verifier(ChunkChecks, SummaryChecks):
    """One pass over a mapped file; :func:`verify_file` runs it."""

    def __init__(self, path: Path, mm: mmap.mmap, buf: memoryview) -> None:
        self.path, self.mm, self.buf, self.n = path, mm, buf, len(buf)
        self.out = Verification(path, self.n)
        self.strict = True
        self.header: Header | None = None
        self.footer: Footer | None = None
        self.footer_at = self.n - 8 - FOOTER_BYTES
        self.chunks: list[ChunkAt] = []
        self.metadata: dict[int, tuple[int, str, dict[str, str]]] = {}  # offset -> (len, name, map)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.data_end_at: int | None = None
        # the summary as parsed (trusted or not: what it says serves to name damage)
        self.summary_ok = False
        self.s_schemas: dict[int, Schema] = {}
        self.s_channels: dict[int, Channel] = {}
        self.s_chunk_indexes: list[ChunkIndex] = []
        self.s_index_places: list[tuple[int, int]] = []  # (at, length) of each
        self.s_metadata_indexes: list[tuple[int, int, Any]] = []
        self.s_statistics: tuple[int, int, Statistics] | None = None
        self.s_offsets: list[tuple[int, int, Any]] = []
        self.s_groups: dict[int, list[tuple[int, int]]] = {}  # opcode -> [(at, length)]
        self.s_parsed_to: int | None = None  # where summary parsing stopped (None: the end)
        self.damaged: list[Damage] = []
        self.batch: list[tuple[ChunkAt, bytes]] = []  # intact chunks waiting for check_batch
        self.batch_bytes = 0
        self._by_offset: list[ChunkIndex] | None = None
        self._offsets: list[int] = []
        self.unreadable = False  # a stretch of the data section held no readable record
        self.cut_topics: tuple[str, ...] = ()  # of a message index cut off after its chunk

    # -------------------------------------------------------------- helpers

    def damage(self, at: int, length: int, record: str, what: str, **kw: Any) -> None:
        self.damaged.append(Damage(at, length, what, record=record, **kw))

    def topics_of(self, ids: Any) -> tuple[str, ...]:
        names = set()
        for cid in ids:
            ch = self.channels.get(cid) or self.s_channels.get(cid)
            if ch is not None:
                names.add(ch.topic)
            elif self.strict and our_topic(cid) is not None:
                names.add(our_topic(cid))
            else:
                names.add(f"channel {cid}")
        return tuple(sorted(names))

    def index_for(self, at: int, end: int) -> ChunkIndex | None:
        """The summary's chunk index entry whose chunk overlaps [at, end), if any."""
        if self._by_offset is None:
            self._by_offset = sorted(self.s_chunk_indexes, key=lambda c: c.chunk_start_offset)
            self._offsets = [c.chunk_start_offset for c in self._by_offset]
        k = bisect.bisect_right(self._offsets, at) - 1
        for ci in self._by_offset[max(k, 0) : k + 2]:
            if ci.chunk_start_offset < end and at < ci.chunk_start_offset + ci.chunk_length:
                return ci
        k = bisect.bisect_left(self._offsets, at)
        if k < len(self._offsets) and self._offsets[k] < end:
            return self._by_offset[k]
        return None

    # -------------------------------------------------------------- the run

    def run(self) -> Verification:
        if self.n < 8 and MAGIC.startswith(bytes(self.buf)):
            return self.out  # created, nothing written (or nothing made durable)
        header = read_header(self.buf)
        # ours (checked strictly: our writer always writes CRCs and indexes): the header names
        # loopcal, or is not intact
        self.strict = header is None or not header.library or header.library.startswith("loopcal")
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
        self.out.chunk_spans = [(c.start_ns, c.end_ns, self.topics_of(c.counts))
                                for c in self.chunks if not c.problem]  # fmt: skip
        self.out.damaged = sorted(self.damaged, key=lambda d: (d.offset, d.record))
        return self.out

    # -------------------------------------------------------------- footer, summary

    def read_footer_and_summary(self) -> None:
        buf, n = self.buf, self.n
        if n < 8 + FOOTER_BYTES + 8 or bytes(buf[n - 8 :]) != MAGIC:
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
                self.damage(self.footer_at, FOOTER_BYTES, "footer", "no summary section")
            return
        if not 8 <= footer.summary_start <= self.footer_at or not (
            footer.summary_offset_start == 0
            or footer.summary_start <= footer.summary_offset_start <= self.footer_at
        ):
            self.damage(self.footer_at, FOOTER_BYTES, "footer",
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
                        f"{opcode_name(at[0])} record in the summary section")  # fmt: skip
                self.damage(pos, self.footer_at - pos, "summary", what)
                self.s_parsed_to = pos
                return
            op, length = at
            self.out.records += 1
            body = buf[pos + RECORD_HEAD : pos + RECORD_HEAD + length]
            whole = RECORD_HEAD + length
            try:
                if op == Opcode.CHUNK_INDEX:
                    self.s_chunk_indexes.append(chunk_index(body, unique=True))
                    self.s_index_places.append((pos, whole))
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
                self.damage(pos, whole, opcode_name(op), "its fields do not fit the record")
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
        chunk: ChunkAt | None = None  # the chunk whose message indexes may follow
        trusted_end, starts = pos, []  # the end of the last intact chunk, records since
        while pos < limit:
            at = record_at(buf, pos, limit)
            op = buf[pos]
            if at is None or not known_opcode(op):
                if chunk is not None:
                    # an index of it cut off: its messages' index is not missing, it is cut
                    chunk.cut_index = op == Opcode.MESSAGE_INDEX
                    self.finish_chunk(chunk)
                    chunk = None
                back = self.overran(trusted_end, starts, pos, limit)
                if back is not None:
                    pos, starts = back, []
                    continue
                pos, chunk = self.bad_bytes(pos, limit, cut=at is None and 0x01 <= op <= 0x0F)
                if chunk is not None:
                    self.chunks.append(chunk)
                first = False
                continue
            op, length = at
            whole = RECORD_HEAD + length
            body = buf[pos + RECORD_HEAD : pos + whole]
            self.out.records += 1
            starts.append(pos)
            if op != Opcode.MESSAGE_INDEX and chunk is not None:
                self.finish_chunk(chunk)
                chunk = None
            if first and op != Opcode.HEADER:
                self.damage(8, 0, "header", f"no header record (found a {opcode_name(op)} record)")
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
                if not chunk.problem:
                    trusted_end, starts = pos + whole, []
            elif op == Opcode.MESSAGE_INDEX:
                mi = message_index_at(pos, whole, body)
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
                    self.damage(pos, whole, opcode_name(op), "its fields do not fit the record")
            elif op == Opcode.DATA_END:
                self.check_data_end(pos, whole, body)
                pos += whole
                break
            elif op in (Opcode.FOOTER, *_SUMMARY_OPCODES - {Opcode.SCHEMA, Opcode.CHANNEL}):
                self.damage(pos, whole, opcode_name(op), "a summary record in the data section")
            elif op in (Opcode.ATTACHMENT, Opcode.MESSAGE) or op >= 0x80:
                if self.strict:  # our writer writes neither, nor private records
                    self.damage(pos, whole, opcode_name(op),
                                "a record our writer never writes here")
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
        if whole != DATA_END_BYTES:
            self.damage(pos, whole, "data end", f"{whole} bytes, not {DATA_END_BYTES}")
        if rec.data_section_crc:
            crc = 0
            for p in range(0, pos, _CRC_PIECE):
                crc = zlib.crc32(self.buf[p : min(p + _CRC_PIECE, pos)], crc)
            # damage already named in the data section explains a mismatch; alone, it is
            # damage no other check sees (the header, a metadata value)
            if crc != rec.data_section_crc and not any(d.offset < pos for d in self.damaged):
                self.damage(0, pos, "data section", "data section CRC mismatch (the header or "
                            "a metadata record changed: no other check covers them)")

    def bad_bytes(self, pos: int, limit: int, *, cut: bool) -> tuple[int, ChunkAt | None]:
        """Name the stretch from ``pos`` where no record can be read; returns where to go on
        (the next chunk that checks out, or the data end a footer gives, or ``limit``) and,
        where the summary's chunk index says a chunk lay exactly there and a record starts
        right after it, that chunk (damaged), whose message indexes then follow."""
        buf = self.buf
        ci = self.index_for(pos, pos + 1)
        if ci is not None and ci.chunk_start_offset != pos:
            ci = None
        after = ci.chunk_start_offset + ci.chunk_length if ci is not None else None
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
            topics = self.topics_of(ci.message_index_offsets)
            start_ns, end_ns = ci.message_start_time, ci.message_end_time
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
            return end, ChunkAt(pos, end - pos, start_ns, end_ns, problem=what)
        record = "chunk" if buf[pos] == Opcode.CHUNK or ci is not None else "records"
        if record == "records" and cut and nxt is None:
            record = opcode_name(buf[pos])
            if buf[pos] == Opcode.MESSAGE_INDEX:
                topics = self.cut_topics
        self.unreadable = True
        self.damage(pos, end - pos, record, what, topics=topics, start_ns=start_ns,
                    end_ns=end_ns)  # fmt: skip
        return end, None

    def overran(self, trusted_end: int, starts: list[int], pos: int, limit: int) -> int | None:
        """Where to go back to when the walk reached bytes that are no record at ``pos``
        because a record's length carried it past an intact chunk: that chunk (the record
        whose length ran past it is named damaged), or None if no record did.

        ``starts``: the records walked since ``trusted_end``, the end of the last intact
        chunk."""
        back = next_chunk(self.buf, trusted_end, pos, strict=self.strict, end=limit)
        over = max((s for s in starts if back is not None and s < back), default=None)
        if back is None or over is None:
            return None
        self.damage(over, back - over, opcode_name(self.buf[over]),
                    f"its length runs past the intact chunk at byte {back} (the records "
                    "between were skipped)")  # fmt: skip
        return back

    def resync(self, lo: int, limit: int) -> int | None:
        """The first offset at or after ``lo`` where a chunk that checks out starts, or the
        data end record's (as the footer gives it); None if neither."""
        data_end = None
        if self.footer is not None and self.footer.summary_start >= lo + DATA_END_BYTES:
            data_end = self.footer.summary_start - DATA_END_BYTES
        for ci in sorted(self.s_chunk_indexes, key=lambda c: c.chunk_start_offset):
            at = ci.chunk_start_offset
            if at >= lo and chunk_checks_out(self.buf, at, limit, strict=self.strict):
                if data_end is None or at < data_end:
                    return at
        stop = data_end if data_end is not None else limit
        found = next_chunk(self.buf, lo, stop, strict=self.strict, end=limit)
        return data_end if found is None else found

    # -------------------------------------------------------------- header and metadata

    def check_header_against_metadata(self) -> None:
        own = [(at, v) for at, v in self.metadata.items() if v[1] == "loopcal"]
        if not own:
            return
        at, (length, _, values) = own[0]
        fmt = values.get("format")
        if fmt is not None and fmt not in READ_FORMATS:
            self.damage(at, length, "metadata", format_words(str(fmt)))
        version = values.get("version")
        if version and self.header is not None and self.header.library != f"loopcal {version}":
            self.damage(8, 0, "header", f"library {self.header.library!r}, while the loopcal "
                        f"metadata says version {version!r}")  # fmt: skip


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
        return Verifier(p, mm, buf).run()
    finally:
        buf.release()
        try:
            mm.close()
        except BufferError:  # a view still referenced: the mapping goes with it
            pass


__all__ = ["Damaged", "Verification", "verify_file"]
