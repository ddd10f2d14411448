"""MCAP records taken from a file's bytes only once they are checked: the one parser of
the format's records that the reader, ``loopcal verify`` and the compaction share.

The mcap library's readers trust the length fields they read: a flipped bit in a length
asks for exabytes (MemoryError), a torn write gives a short record that is parsed as a whole
one, an index entry is followed to whatever lies at its offset, and a CRC of 0 switches the
check off. A recording that power loss or flaky storage damaged must instead give back what
is intact and say what is not. This module reads records with every length checked against
the bytes that are there before anything is read, parses each record's fields with the mcap
library's own record classes on a stream that refuses short reads (the chunk and message
indexes, of which a day has tens of thousands, with :mod:`struct`), checks every CRC the
writer wrote, and reports what it cannot trust as a
:class:`~loopcal.daemon.recording.damage.Damage` instead of raising.

- :func:`record_at`, :func:`parse_record`: a record's head, and its fields;
- :func:`chunk_index`, :func:`message_index`: the index records, parsed fast;
- :func:`read_chunk`: one chunk checked (opcode, length, header, size, CRC) and split into
  its records; :func:`chunk_checks_out`, the same without splitting it;
- :func:`next_chunk`: where the next intact chunk starts (resynchronising after damage).

The summary section is :mod:`~loopcal.daemon.recording.mcap_summary`'s, the data section record
by record :mod:`~loopcal.daemon.recording.walk`'s.

``strict`` (a file our own writer wrote: its header names loopcal) makes a CRC of 0 count as
damage, since that writer always writes CRCs; for other files 0 means "not written", as the
MCAP specification says.
"""

from __future__ import annotations

import mmap
import struct
import threading
import zlib
from collections.abc import Callable
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

from .damage import Damage

MAGIC = b"\x89MCAP0\r\n"
#: a record: opcode (1 byte) and length (8 bytes), then the body
RECORD_HEAD = 9
#: the footer record (head and three fields) and the closing magic
FOOTER_BYTES = RECORD_HEAD + 20
#: the data end record (head and its CRC)
DATA_END_BYTES = RECORD_HEAD + 4
#: chunks larger than this uncompressed are taken as damage (a recording's are kilobytes);
#: it bounds what a corrupt size field can make the reader allocate
MAX_CHUNK_BYTES = 1 << 28

HEAD = struct.Struct("<BQ")  # opcode, record length
U64 = struct.Struct("<Q")
CHUNK_FIXED = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, compression length
MESSAGE_FIXED = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # a message record's opcode, length and fixed fields
INDEX_FIXED = struct.Struct("<QQQQI")  # start, end, chunk offset, chunk length, map bytes
INDEX_ENTRY = struct.Struct("<HQ")  # channel id, message index offset
INDEX_TAIL = struct.Struct("<QQ")  # compressed size, uncompressed size
MESSAGE_INDEX_HEAD = struct.Struct("<HI")  # channel id, byte length of the entries
MESSAGE_INDEX_ENTRY = struct.Struct("<QQ")  # log time, offset in the chunk
_COMPRESSIONS = ("", "zstd", "lz4")

#: what parsing a record's fields may raise on damaged bytes
PARSE_ERRORS = (McapError, struct.error, ValueError, UnicodeDecodeError, OverflowError,
                KeyError, IndexError, TypeError, zstandard.ZstdError, zlib.error)  # fmt: skip


@dataclass
class ChunkRecords:
    """What an intact chunk held: its log-time span, the channel and schema records, and
    the messages (channel id, log time, payload) of the channels asked for."""

    offset: int
    start_ns: int
    end_ns: int
    channels: list[Channel] = field(default_factory=list)
    messages: list[tuple[int, int, bytes]] = field(default_factory=list)


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


def parses(opcode: int) -> bool:
    """Whether :func:`parse_record` knows the records of ``opcode``."""
    return opcode in _PARSERS


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
    length = U64.unpack_from(buf, pos + 1)[0]
    if length > end - pos - RECORD_HEAD:
        return None
    return buf[pos], length


def known_opcode(op: int) -> bool:
    """Whether ``op`` may start a record: 0x01..0x0F are the specification's records,
    0x80..0xFF are reserved for private records that a reader skips; anything else is not
    the start of a record."""
    return 0x01 <= op <= 0x0F or op >= 0x80


def opcode_name(op: int) -> str:
    """A record's kind for people: ``message index``, or ``opcode 0x42``."""
    try:
        return Opcode(op).name.lower().replace("_", " ")
    except ValueError:
        return f"opcode 0x{op:02x}"


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


# ---------------------------------------------------------------------------- indexes


def chunk_index(body: memoryview, *, unique: bool = False) -> ChunkIndex:
    """A chunk index record's body, parsed with every length checked (a day of recording has
    86,400 of them: the library's field-by-field reader is the slow part of a read). Raises
    ValueError if the fields do not fill the body exactly, or, when ``unique``, if its map
    names a channel twice."""
    n = len(body)
    if n < INDEX_FIXED.size + 8 + 4 + 16:
        raise ValueError("short chunk index")
    start, end, offset, length, map_len = INDEX_FIXED.unpack_from(body, 0)
    pos = INDEX_FIXED.size
    if map_len % INDEX_ENTRY.size or pos + map_len + 12 > n:
        raise ValueError("chunk index map overruns the record")
    entries = list(INDEX_ENTRY.iter_unpack(body[pos : pos + map_len]))
    offsets = dict(entries)
    if unique and len(offsets) != len(entries):
        raise ValueError("a channel twice in the chunk index's map")
    pos += map_len
    (index_len,) = U64.unpack_from(body, pos)
    (clen,) = struct.unpack_from("<I", body, pos + 8)
    pos += 12
    if pos + clen + INDEX_TAIL.size != n:
        raise ValueError("chunk index fields do not fill the record")
    compression = bytes(body[pos : pos + clen]).decode("utf-8")
    csize, usize = INDEX_TAIL.unpack_from(body, pos + clen)
    return ChunkIndex(
        message_start_time=start, message_end_time=end, chunk_start_offset=offset,
        chunk_length=length, message_index_offsets=offsets, message_index_length=index_len,
        compression=compression, compressed_size=csize, uncompressed_size=usize,
    )  # fmt: skip


def message_index_entries(body: memoryview) -> tuple[int, memoryview]:
    """A message index record's channel id and its entries (16 bytes each: log time and
    offset in the chunk, little-endian uint64), the length checked. Raises ValueError if
    the entries do not fill the body exactly."""
    if len(body) < MESSAGE_INDEX_HEAD.size:
        raise ValueError("short message index")
    channel, size = MESSAGE_INDEX_HEAD.unpack_from(body, 0)
    if size % MESSAGE_INDEX_ENTRY.size or MESSAGE_INDEX_HEAD.size + size != len(body):
        raise ValueError("message index entries do not fill the record")
    return channel, body[MESSAGE_INDEX_HEAD.size :]


def message_index(body: memoryview) -> MessageIndex:
    """A message index record's body, parsed with its length checked (what the mcap
    library's reader gives, without its field-by-field reads). Raises ValueError as
    :func:`message_index_entries` does."""
    channel, entries = message_index_entries(body)
    return MessageIndex(channel_id=channel, records=list(MESSAGE_INDEX_ENTRY.iter_unpack(entries)))


# ---------------------------------------------------------------------------- chunks


def chunk_header(body: memoryview) -> tuple[int, int, int, int, str, memoryview] | None:
    """(start, end, uncompressed size, CRC, compression, compressed data) of a chunk body
    whose fields are consistent with its length, else None."""
    if len(body) < CHUNK_FIXED.size + 8:
        return None
    start, end, usize, crc, clen = CHUNK_FIXED.unpack_from(body, 0)
    pos = CHUNK_FIXED.size
    if clen > 8 or pos + clen + 8 > len(body):
        return None
    try:
        compression = bytes(body[pos : pos + clen]).decode("ascii")
    except UnicodeDecodeError:
        return None
    pos += clen
    (dlen,) = U64.unpack_from(body, pos)
    pos += 8
    if compression not in _COMPRESSIONS or dlen != len(body) - pos or end < start:
        return None
    return start, end, usize, crc, compression, body[pos:]


def is_chunk_body(body: memoryview) -> bool:
    """Whether ``body`` is a chunk record's body whose header fields are consistent with
    its length (a chunk, whatever its opcode byte now says)."""
    return chunk_header(body) is not None


_local = threading.local()  # a zstd decompressor per thread (one is not thread-safe)


def decompress(compression: str, data: memoryview, size: int) -> bytes:
    """A chunk's records: ``data`` decompressed to exactly ``size`` bytes (never more).

    Raises ValueError if it decompresses to another size, one of PARSE_ERRORS if it does
    not decompress, ImportError for lz4 without its package."""
    if compression == "":
        out = bytes(data)
    elif compression == "zstd":
        params = zstandard.get_frame_parameters(data)
        if params.content_size not in (size, zstandard.CONTENTSIZE_UNKNOWN):
            raise ValueError("zstd frame size differs from the chunk's")
        zstd = getattr(_local, "zstd", None)
        if zstd is None:
            zstd = _local.zstd = zstandard.ZstdDecompressor()
        out = zstd.decompress(data, max_output_size=size)
    else:
        import lz4.frame  # optional: only files written by other tools use it

        out = lz4.frame.decompress(bytes(data))
    if len(out) != size:
        raise ValueError("decompressed size differs from the chunk's")
    return out


def checked_chunk(head: tuple, *, strict: bool) -> bytes | str:
    """A chunk's records (its header ``head`` as :func:`chunk_header` gives it),
    decompressed and CRC-checked, or what is wrong: ``"without CRC"`` (a CRC of 0 when
    ``strict``), ``"claims N bytes uncompressed"``, ``"does not decompress"``, ``"CRC
    mismatch"``."""
    _start, _end, usize, crc, compression, data = head
    if crc == 0 and strict:
        return "without CRC"
    if usize > MAX_CHUNK_BYTES:
        return f"claims {usize} bytes uncompressed"
    try:
        raw = decompress(compression, data, usize)
    except (ImportError, *PARSE_ERRORS):
        return "does not decompress"
    if crc != 0 and zlib.crc32(raw) != crc:
        return "CRC mismatch"
    return raw


def chunk_checks_out(buf: memoryview, pos: int, end: int, *, strict: bool) -> bool:
    """Whether a chunk record that fits before ``end`` starts at ``pos`` and checks out:
    its header, its size, decompression and CRC (its records are not split)."""
    at = record_at(buf, pos, end)
    if at is None or at[0] != Opcode.CHUNK:
        return False
    head = chunk_header(buf[pos + RECORD_HEAD : pos + RECORD_HEAD + at[1]])
    return head is not None and isinstance(checked_chunk(head, strict=strict), bytes)


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
    start, end = head[0], head[1]

    def damage(what: str) -> Damage:
        return Damage(pos, RECORD_HEAD + length, what, start, end)

    raw = checked_chunk(head, strict=strict)
    if isinstance(raw, str):
        return damage(f"chunk {raw}")
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
                if rlen < MESSAGE_FIXED.size:
                    return damage("short message record")
                cid, _seq, log_time, _pub = MESSAGE_FIXED.unpack_from(view, b)
                if wanted is None or cid in wanted:
                    out.messages.append(
                        (cid, log_time, bytes(view[b + MESSAGE_FIXED.size : b + rlen]))
                    )
            elif op == Opcode.CHANNEL:
                out.channels.append(parse_record(op, view[b : b + rlen]))
            p = b + rlen
    except PARSE_ERRORS:
        return damage("damaged record inside the chunk")
    return out


def next_chunk(
    buf: memoryview, lo: int, stop: int, *, strict: bool, end: int | None = None,
    skip: int = -1,
) -> int | None:  # fmt: skip
    """Resynchronise after damage: the offset of the first chunk starting in [lo, stop)
    that checks out (:func:`chunk_checks_out`, fitting before ``end``, the end of ``buf``
    by default), other than the record at ``skip``; None if there is none."""
    whole = isinstance(buf.obj, (bytes, mmap.mmap)) and len(buf.obj) == len(buf)
    data = buf.obj if whole else bytes(buf)
    end = len(buf) if end is None else end
    p = lo
    while True:
        p = data.find(b"\x06", p, stop)
        if p < 0:
            return None
        if p != skip and chunk_checks_out(buf, p, end, strict=strict):
            return p
        p += 1


__all__ = [
    "DATA_END_BYTES",
    "FOOTER_BYTES",
    "MAGIC",
    "MAX_CHUNK_BYTES",
    "PARSE_ERRORS",
    "RECORD_HEAD",
    "ChunkRecords",
    "Damage",
    "checked_chunk",
    "chunk_checks_out",
    "chunk_header",
    "chunk_index",
    "decompress",
    "is_chunk_body",
    "is_ours",
    "known_opcode",
    "message_index",
    "message_index_entries",
    "next_chunk",
    "opcode_name",
    "parse_record",
    "read_chunk",
    "read_header",
    "record_at",
]
