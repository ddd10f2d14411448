"""MCAP records taken from a file's bytes only once they are checked.

The mcap library's readers trust the length fields they read: a flipped bit in a length
asks for exabytes (MemoryError), a torn write gives a short record that is parsed as a whole
one, an index entry is followed to whatever lies at its offset, and a CRC of 0 switches the
check off. A recording that power loss or flaky storage damaged must instead give back what
is intact and say what is not. This module walks the same records with every length checked
against the bytes that are there before anything is read, parses each record's fields with
the mcap library's own record classes on a stream that refuses short reads, checks every CRC
the writer wrote, and reports what it cannot trust as a :class:`Damage` instead of raising.

- :func:`read_summary`: the summary section, only if the footer is intact and the summary's
  CRC matches (its chunk index is then what the writer wrote when it closed the file);
- :func:`walk`: the data section record by record, for a file without a usable summary;
  after a record that cannot be trusted it resynchronises on the next intact chunk;
- :func:`read_chunk`: one chunk checked (opcode, length, header, size, CRC) and split into
  its records.

``strict`` (a file our own writer wrote: its header names loopcal) makes a CRC of 0 count as
damage, since that writer always writes CRCs; for other files 0 means "not written", as the
MCAP specification says.
"""

from __future__ import annotations

import mmap
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from io import BytesIO
from typing import Any

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
#: a record: opcode (1 byte) and length (8 bytes), then the body
RECORD_HEAD = 9
#: the footer record (head and three fields) and the closing magic
FOOTER_BYTES = RECORD_HEAD + 20
#: chunks larger than this uncompressed are taken as damage (a recording's are kilobytes);
#: it bounds what a corrupt size field can make the reader allocate
MAX_CHUNK_BYTES = 1 << 28
#: how far the resynchronisation looks for the next intact chunk after damage (bytes)
_RESYNC_WINDOW = 1 << 30

_CHUNK_FIXED = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, compression length
_MESSAGE_FIXED = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_U64 = struct.Struct("<Q")
_COMPRESSIONS = ("", "zstd", "lz4")

#: what parsing a record's fields may raise on damaged bytes
PARSE_ERRORS = (McapError, struct.error, ValueError, UnicodeDecodeError, OverflowError,
                KeyError, IndexError, TypeError, zstandard.ZstdError, zlib.error)  # fmt: skip


@dataclass(frozen=True)
class Damage:
    """A part of the file that could not be trusted.

    Attributes
    ----------
    offset : int
        Its first byte.
    length : int
        Bytes it spans (0 when unknown).
    what : str
        One phrase for people (e.g. ``"chunk CRC mismatch"``).
    start_ns : int or None, default None
        Log time of the first message it held, ns since the Unix epoch, when a readable
        chunk header or index entry says so.
    end_ns : int or None, default None
        Log time of the last message it held, likewise.
    """

    offset: int
    length: int
    what: str
    start_ns: int | None = None
    end_ns: int | None = None


@dataclass
class ChunkRecords:
    """What an intact chunk held: its log-time span, the channel and schema records, and
    the messages (channel id, log time, payload) of the channels asked for."""

    offset: int
    start_ns: int
    end_ns: int
    channels: list[Channel] = field(default_factory=list)
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)


@dataclass
class Summary:
    """A summary section whose CRC matched."""

    channels: dict[int, Channel]
    statistics: Statistics | None
    chunk_indexes: list[ChunkIndex]
    metadata_indexes: list[MetadataIndex]


class _Strict(ReadDataStream):
    """A ReadDataStream that refuses short reads (the library's returns what there is)."""

    def read(self, length: int) -> bytes:
        if length < 0:
            raise EndOfFile()
        data = super().read(length)
        if len(data) != length:
            raise EndOfFile()
        return data


_PARSERS: dict[int, Callable[[ReadDataStream, int], McapRecord]] = {
    Opcode.HEADER: lambda s, n: Header.read(s),
    Opcode.FOOTER: lambda s, n: Footer.read(s),
    Opcode.SCHEMA: lambda s, n: Schema.read(s),
    Opcode.CHANNEL: lambda s, n: Channel.read(s),
    Opcode.MESSAGE: Message.read,
    Opcode.MESSAGE_INDEX: lambda s, n: MessageIndex.read(s),
    Opcode.CHUNK_INDEX: lambda s, n: ChunkIndex.read(s),
    Opcode.METADATA: lambda s, n: Metadata.read(s),
    Opcode.METADATA_INDEX: lambda s, n: MetadataIndex.read(s),
    Opcode.STATISTICS: lambda s, n: Statistics.read(s),
    Opcode.SUMMARY_OFFSET: lambda s, n: SummaryOffset.read(s),
    Opcode.DATA_END: lambda s, n: DataEnd.read(s),
}


def parse_record(opcode: int, body: bytes | memoryview) -> Any:
    """The record of ``opcode`` whose body is exactly ``body``, parsed by the mcap library's
    record class (None for an opcode it does not know). Raises one of PARSE_ERRORS if the
    fields do not fit in the body."""
    parser = _PARSERS.get(opcode)
    if parser is None:
        return None
    stream = _Strict(BytesIO(body))
    return parser(stream, len(body))


def record_at(buf: memoryview, pos: int, end: int) -> tuple[int, int] | None:
    """(opcode, body length) of the record starting at ``pos`` if its body fits before
    ``end``, else None."""
    if pos + RECORD_HEAD > end:
        return None
    length = _U64.unpack_from(buf, pos + 1)[0]
    if length > end - pos - RECORD_HEAD:
        return None
    return buf[pos], length


def _known_opcode(op: int) -> bool:
    # 0x01..0x0F are the specification's records; 0x80..0xFF are reserved for private
    # records that a reader skips. Anything else is not the start of a record.
    return 0x01 <= op <= 0x0F or op >= 0x80


# ---------------------------------------------------------------------------- summary


def read_header(buf: memoryview) -> Header | None:
    """The header record right after the magic, or None if it is not intact."""
    if bytes(buf[:8]) != MAGIC:
        return None
    at = record_at(buf, 8, len(buf))
    if at is None or at[0] != Opcode.HEADER:
        return None
    try:
        return parse_record(Opcode.HEADER, buf[8 + RECORD_HEAD : 8 + RECORD_HEAD + at[1]])
    except PARSE_ERRORS:
        return None


def is_ours(header: Header | None) -> bool:
    """Whether a file is taken to be written by loopcal (its records then checked strictly):
    its header names the loopcal library, or is not intact (a damaged start)."""
    return header is None or header.library.startswith("loopcal")


def _footer(buf: memoryview, *, strict: bool, base: int) -> tuple[Footer | None, str]:
    """The footer of a file whose summary's CRC matches, or (None, why not). ``buf`` holds
    the file from offset ``base`` to its end."""
    n = len(buf)
    if n < FOOTER_BYTES + 8 or bytes(buf[n - 8 :]) != MAGIC:
        return None, "no footer (the file was not closed)"
    fpos = n - 8 - FOOTER_BYTES
    at = record_at(buf, fpos, n - 8)
    if at is None or at != (Opcode.FOOTER, 20):
        return None, "damaged footer"
    try:
        footer: Footer = parse_record(Opcode.FOOTER, buf[fpos + RECORD_HEAD : n - 8])
    except PARSE_ERRORS:
        return None, "damaged footer"
    start, offsets_at = footer.summary_start - base, footer.summary_offset_start - base
    if footer.summary_start == 0:
        return None, "no summary section"
    if not max(0, 8 - base) <= start <= fpos or not (
        footer.summary_offset_start == 0 or start <= offsets_at <= fpos
    ):
        return None, "footer points outside the file"
    if footer.summary_crc == 0:
        if strict:
            return None, "summary without CRC"
    elif zlib.crc32(buf[start : fpos + RECORD_HEAD + 16]) != footer.summary_crc:
        return None, "summary CRC mismatch"
    return footer, ""


def read_summary(
    buf: memoryview, *, strict: bool, base: int = 0
) -> tuple[Summary | None, str]:
    """The summary of a closed file, or (None, why not).

    buf: the file's bytes from offset ``base`` to its end (the whole file by default; a
    reader that wants only the summary passes its tail). Trusted only if the file ends in
    magic and footer, the footer's offsets point inside the file, and the summary's CRC
    matches (a CRC of 0 is refused when ``strict``).
    """
    footer, why = _footer(buf, strict=strict, base=base)
    if footer is None:
        return None, why
    fpos = len(buf) - 8 - FOOTER_BYTES
    summary = Summary({}, None, [], [])
    pos = footer.summary_start - base
    while pos < fpos:
        at = record_at(buf, pos, fpos)
        if at is None or not _known_opcode(at[0]):
            return None, f"damaged summary record at byte {base + pos}"
        op, length = at
        body = buf[pos + RECORD_HEAD : pos + RECORD_HEAD + length]
        try:
            rec = _chunk_index(body) if op == Opcode.CHUNK_INDEX else parse_record(op, body)
        except PARSE_ERRORS:
            return None, f"damaged summary record at byte {base + pos}"
        if isinstance(rec, Channel):
            summary.channels[rec.id] = rec
        elif isinstance(rec, ChunkIndex):
            summary.chunk_indexes.append(rec)
        elif isinstance(rec, MetadataIndex):
            summary.metadata_indexes.append(rec)
        elif isinstance(rec, Statistics):
            summary.statistics = rec
        pos += RECORD_HEAD + length
    return summary, ""


def read_statistics(buf: memoryview, *, strict: bool, base: int = 0) -> Statistics | None:
    """The statistics record of a closed file (as :func:`read_summary` trusts it), found
    through the summary offsets without parsing the rest of the summary; None if absent."""
    footer, _ = _footer(buf, strict=strict, base=base)
    if footer is None:
        return None
    fpos = len(buf) - 8 - FOOTER_BYTES
    pos = footer.summary_offset_start - base
    if footer.summary_offset_start == 0:
        summary, _ = read_summary(buf, strict=strict, base=base)
        return None if summary is None else summary.statistics
    try:
        while pos < fpos:
            at = record_at(buf, pos, fpos)
            if at is None or at[0] != Opcode.SUMMARY_OFFSET:
                return None
            rec = parse_record(Opcode.SUMMARY_OFFSET, buf[pos + RECORD_HEAD :
                                                          pos + RECORD_HEAD + at[1]])
            pos += RECORD_HEAD + at[1]
            if rec.group_opcode == Opcode.STATISTICS:
                g = rec.group_start - base
                at = record_at(buf, g, fpos)
                if at is None or at[0] != Opcode.STATISTICS:
                    return None
                return parse_record(Opcode.STATISTICS, buf[g + RECORD_HEAD :
                                                           g + RECORD_HEAD + at[1]])
    except PARSE_ERRORS:
        return None
    return None


_INDEX_FIXED = struct.Struct("<QQQQI")  # start, end, chunk offset, chunk length, map bytes
_INDEX_ENTRY = struct.Struct("<HQ")  # channel id, message index offset
_INDEX_TAIL = struct.Struct("<QQ")  # compressed size, uncompressed size


def _chunk_index(body: memoryview) -> ChunkIndex:
    """A chunk index record's body, parsed with every length checked (a day of recording has
    86,400 of them: the library's field-by-field reader is the slow part of a read). Raises
    ValueError if the fields do not fill the body exactly."""
    n = len(body)
    if n < _INDEX_FIXED.size + 8 + 4 + 16:
        raise ValueError("short chunk index")
    start, end, offset, length, map_len = _INDEX_FIXED.unpack_from(body, 0)
    pos = _INDEX_FIXED.size
    if map_len % _INDEX_ENTRY.size or pos + map_len + 12 > n:
        raise ValueError("chunk index map overruns the record")
    offsets = dict(_INDEX_ENTRY.iter_unpack(body[pos : pos + map_len]))
    pos += map_len
    (index_len,) = _U64.unpack_from(body, pos)
    (clen,) = struct.unpack_from("<I", body, pos + 8)
    pos += 12
    if pos + clen + _INDEX_TAIL.size != n:
        raise ValueError("chunk index fields do not fill the record")
    compression = bytes(body[pos : pos + clen]).decode("utf-8")
    csize, usize = _INDEX_TAIL.unpack_from(body, pos + clen)
    return ChunkIndex(
        message_start_time=start, message_end_time=end, chunk_start_offset=offset,
        chunk_length=length, message_index_offsets=offsets, message_index_length=index_len,
        compression=compression, compressed_size=csize, uncompressed_size=usize,
    )  # fmt: skip


# ---------------------------------------------------------------------------- chunks


def chunk_header(body: memoryview) -> tuple[int, int, int, int, str, memoryview] | None:
    """(start, end, uncompressed size, CRC, compression, compressed data) of a chunk body
    whose fields are consistent with its length, else None."""
    if len(body) < _CHUNK_FIXED.size + 8:
        return None
    start, end, usize, crc, clen = _CHUNK_FIXED.unpack_from(body, 0)
    pos = _CHUNK_FIXED.size
    if clen > 8 or pos + clen + 8 > len(body):
        return None
    try:
        compression = bytes(body[pos : pos + clen]).decode("ascii")
    except UnicodeDecodeError:
        return None
    pos += clen
    (dlen,) = _U64.unpack_from(body, pos)
    pos += 8
    if compression not in _COMPRESSIONS or dlen != len(body) - pos or end < start:
        return None
    return start, end, usize, crc, compression, body[pos:]


def is_chunk_body(body: memoryview) -> bool:
    """Whether ``body`` is a chunk record's body whose header fields are consistent with
    its length (a chunk, whatever its opcode byte now says)."""
    return chunk_header(body) is not None


def _decompress(compression: str, data: memoryview, size: int) -> bytes:
    if compression == "":
        return bytes(data)
    if compression == "zstd":
        params = zstandard.get_frame_parameters(data)
        if params.content_size not in (size, zstandard.CONTENTSIZE_UNKNOWN):
            raise ValueError("zstd frame size differs from the chunk's")
        out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    else:
        import lz4.frame  # optional: only files written by other tools use it

        out = lz4.frame.decompress(bytes(data))
    if len(out) != size:
        raise ValueError("decompressed size differs from the chunk's")
    return out


def read_chunk(
    buf: memoryview,
    pos: int,
    *,
    strict: bool,
    wanted: set[int] | None,
    expected_length: int | None = None,
) -> ChunkRecords | Damage:
    """The chunk record at byte ``pos``, checked, or a :class:`Damage` saying why not.

    wanted: channel ids whose messages to keep (None: all). expected_length: the record's
    length (head included) as an index gives it, which must match.
    """
    at = record_at(buf, pos, len(buf))
    if at is None or at[0] != Opcode.CHUNK:
        return Damage(pos, expected_length or 0, "no chunk where the index says")
    length = at[1]
    if expected_length is not None and expected_length != RECORD_HEAD + length:
        return Damage(pos, expected_length, "chunk length differs from the index")
    body = buf[pos + RECORD_HEAD : pos + RECORD_HEAD + length]
    head = chunk_header(body)
    if head is None:
        return Damage(pos, RECORD_HEAD + length, "damaged chunk header")
    start, end, usize, crc, compression, data = head

    def damage(what: str) -> Damage:
        return Damage(pos, RECORD_HEAD + length, what, start, end)

    if crc == 0 and strict:
        return damage("chunk without CRC")
    if usize > MAX_CHUNK_BYTES:
        return damage(f"chunk claims {usize} bytes uncompressed")
    try:
        raw = _decompress(compression, data, usize)
    except (ImportError, *PARSE_ERRORS):
        return damage("chunk does not decompress")
    if crc != 0 and zlib.crc32(raw) != crc:
        return damage("chunk CRC mismatch")
    out = ChunkRecords(pos, start, end)
    view = memoryview(raw)
    p, n = 0, len(raw)
    try:
        while p < n:
            at = record_at(view, p, n)
            if at is None:
                return damage("chunk records overrun the chunk")
            op, rlen = at
            b = p + RECORD_HEAD
            if op == Opcode.MESSAGE:
                if rlen < _MESSAGE_FIXED.size:
                    return damage("short message record")
                cid, _seq, log_time, _pub = _MESSAGE_FIXED.unpack_from(view, b)
                if wanted is None or cid in wanted:
                    out.messages.append(
                        (cid, log_time, bytes(view[b + _MESSAGE_FIXED.size : b + rlen]))
                    )
            elif op == Opcode.CHANNEL:
                out.channels.append(parse_record(op, view[b : b + rlen]))
            p = b + rlen
    except PARSE_ERRORS:
        return damage("damaged record inside the chunk")
    return out


# ---------------------------------------------------------------------------- data section


def walk(
    buf: memoryview, *, strict: bool, wanted: Callable[[], set[int] | None]
) -> Iterator[ChunkRecords | Damage | McapRecord]:
    """The data section's records in file order, for a file without a usable summary.

    Yields each intact chunk as :class:`ChunkRecords` (messages of the channels
    ``wanted()`` names at that moment), each other record the mcap library's record object,
    and a :class:`Damage` for each stretch that cannot be trusted. Stops at the data end,
    the footer (of their size, in a file that ends in MCAP magic: anything else with their
    opcode is damage) or the end of the bytes. After damage it resumes at the next intact
    chunk, looking from the end of the last chunk that checked out (a bad length may have carried
    the walk past good chunks). A record cut off by the end of the file is reported as
    damage ("cut off").
    """
    n = len(buf)
    pos = 8 if bytes(buf[:8]) == MAGIC else 0
    if pos == 0:
        yield Damage(0, 8, "no MCAP magic at the start")
    trusted_end = pos  # the end of the last record verified by a CRC
    while pos < n:
        at = record_at(buf, pos, n)
        op = buf[pos]
        if at is None or not _known_opcode(op):
            damage = _damage_at(buf, pos, at is None and _known_opcode(op))
            resync = _resync(buf, max(trusted_end, 8 if pos > 8 else pos + 1), pos, strict)
            if resync is None:
                yield Damage(damage.offset, n - damage.offset, damage.what,
                             damage.start_ns, damage.end_ns)  # fmt: skip
                return
            yield Damage(damage.offset, max(0, resync - damage.offset), damage.what,
                         damage.start_ns, damage.end_ns)  # fmt: skip
            pos = resync
            continue
        op, length = at
        end = pos + RECORD_HEAD + length
        if op == Opcode.CHUNK:
            got = read_chunk(buf, pos, strict=strict, wanted=wanted())
            if isinstance(got, ChunkRecords):
                trusted_end = end
            yield got
        elif op in (Opcode.DATA_END, Opcode.FOOTER):
            if _is_end(buf, pos, op, length):
                return
            # a chunk whose opcode was hit, or junk: not the end of the data
            yield Damage(pos, end - pos, f"a {Opcode(op).name.lower()} record that is not the end")
        elif op == Opcode.MESSAGE_INDEX:  # one per channel and chunk: parsed in C
            try:
                yield _message_index(buf[pos + RECORD_HEAD : end])
            except PARSE_ERRORS:
                yield Damage(pos, end - pos, "damaged message_index record")
        elif op in _PARSERS:
            try:
                yield parse_record(op, buf[pos + RECORD_HEAD : end])
            except PARSE_ERRORS:
                yield Damage(pos, end - pos, f"damaged {Opcode(op).name.lower()} record")
        pos = end


_MESSAGE_INDEX_HEAD = struct.Struct("<HI")  # channel id, byte length of the entries
_MESSAGE_INDEX_ENTRY = struct.Struct("<QQ")  # log time, offset in the chunk


def _message_index(body: memoryview) -> MessageIndex:
    """A message index record's body, parsed with its length checked (what the mcap
    library's reader gives, without its field-by-field reads). Raises ValueError if the
    entries do not fill the body exactly."""
    if len(body) < _MESSAGE_INDEX_HEAD.size:
        raise ValueError("short message index")
    channel, size = _MESSAGE_INDEX_HEAD.unpack_from(body, 0)
    if size % _MESSAGE_INDEX_ENTRY.size or _MESSAGE_INDEX_HEAD.size + size != len(body):
        raise ValueError("message index entries do not fill the record")
    entries = body[_MESSAGE_INDEX_HEAD.size :]
    return MessageIndex(channel_id=channel, records=list(_MESSAGE_INDEX_ENTRY.iter_unpack(entries)))


def _is_end(buf: memoryview, pos: int, op: int, length: int) -> bool:
    """Whether a data end or footer record at ``pos`` ends the data section: of its size,
    in a file that ends in MCAP magic (a footer: right before it)."""
    n = len(buf)
    if n < 8 or bytes(buf[n - 8 :]) != MAGIC:
        return False
    if op == Opcode.FOOTER:
        return length == FOOTER_BYTES - RECORD_HEAD and pos + FOOTER_BYTES + 8 == n
    return length == 4


def _damage_at(buf: memoryview, pos: int, cut_off: bool) -> Damage:
    """Describe what lies at ``pos`` where no record could be read."""
    n = len(buf)
    if cut_off:
        what = "cut off: the last record is incomplete"
        if buf[pos] == Opcode.CHUNK and pos + RECORD_HEAD + 16 <= n:
            start, end = struct.unpack_from("<QQ", buf, pos + RECORD_HEAD)
            if end >= start:
                return Damage(pos, n - pos, what, start, end)
        return Damage(pos, n - pos, what)
    if not any(buf[pos : pos + RECORD_HEAD]):
        return Damage(pos, 0, "zeros where records should be (a torn write or power loss)")
    return Damage(pos, 0, "no valid record")


def _resync(buf: memoryview, lo: int, bad: int, strict: bool) -> int | None:
    """The offset of the first chunk at or after ``lo`` (but not the record at ``bad``
    itself) that reads back intact, or None."""
    whole = isinstance(buf.obj, (bytes, mmap.mmap)) and len(buf.obj) == len(buf)
    data = buf.obj if whole else bytes(buf)
    n = len(buf)
    p = lo
    limit = min(n, bad + _RESYNC_WINDOW)
    while True:
        p = data.find(b"\x06", p, limit)
        if p < 0:
            return None
        if p != bad:
            at = record_at(buf, p, n)
            if at is not None and chunk_header(buf[p + RECORD_HEAD : p + RECORD_HEAD + at[1]]):
                got = read_chunk(buf, p, strict=strict, wanted=set())
                if isinstance(got, ChunkRecords):
                    return p
        p += 1


__all__ = [
    "MAGIC",
    "MAX_CHUNK_BYTES",
    "PARSE_ERRORS",
    "ChunkRecords",
    "Damage",
    "Summary",
    "is_chunk_body",
    "is_ours",
    "parse_record",
    "read_chunk",
    "read_header",
    "read_statistics",
    "read_summary",
    "record_at",
    "walk",
]
