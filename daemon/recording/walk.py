"""The data section record by record, for a file without a usable summary.

:func:`walk` yields each intact chunk, each other record and each stretch that cannot be
trusted, in file order, resynchronising on the next intact chunk after damage. The records
are :mod:`~loopcal.daemon.recording.mcap_records`'.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator

from mcap.opcode import Opcode
from mcap.records import McapRecord

from .damage import Damage
from .mcap_records import (
    FOOTER_BYTES,
    MAGIC,
    PARSE_ERRORS,
    RECORD_HEAD,
    ChunkRecords,
    known_opcode,
    message_index,
    next_chunk,
    parse_record,
    parses,
    read_chunk,
    record_at,
)

#: what a record is called whose length ran past an intact chunk (the bytes it covered held
#: records the walk never read)
OVERRAN = "a record length that ran past an intact chunk (the records it covered were skipped)"

#: how far the resynchronisation looks for the next intact chunk after damage (bytes)
_RESYNC_WINDOW = 1 << 30


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
    starts: list[int] = []  # where the records walked since trusted_end start
    while pos < n:
        at = record_at(buf, pos, n)
        op = buf[pos]
        if at is None or not known_opcode(op):
            damage = _damage_at(buf, pos, at is None and known_opcode(op))
            resync = next_chunk(buf, max(trusted_end, 8 if pos > 8 else pos + 1),
                                min(n, pos + _RESYNC_WINDOW), strict=strict, skip=pos)
            if resync is None:
                yield Damage(damage.offset, n - damage.offset, damage.what,
                             damage.start_ns, damage.end_ns)  # fmt: skip
                return
            if resync < pos:
                # a record's length carried the walk past an intact chunk: what it covered
                # was never read, and the walk goes back to read from that chunk on
                over = max((s for s in starts if s < resync), default=trusted_end)
                yield Damage(over, resync - over, OVERRAN)
            else:
                yield Damage(damage.offset, resync - damage.offset, damage.what,
                             damage.start_ns, damage.end_ns)  # fmt: skip
            pos = resync
            starts = []
            continue
        starts.append(pos)
        op, length = at
        end = pos + RECORD_HEAD + length
        if op == Opcode.CHUNK:
            got = read_chunk(buf, pos, strict=strict, wanted=wanted())
            if isinstance(got, ChunkRecords):
                trusted_end = end
                starts = []
            yield got
        elif op in (Opcode.DATA_END, Opcode.FOOTER):
            if _is_end(buf, pos, op, length):
                return
            # a chunk whose opcode was hit, or junk: not the end of the data
            yield Damage(pos, end - pos, f"a {Opcode(op).name.lower()} record that is not the end")
        elif op == Opcode.MESSAGE_INDEX:  # one per channel and chunk: parsed in C
            try:
                yield message_index(buf[pos + RECORD_HEAD : end])
            except PARSE_ERRORS:
                yield Damage(pos, end - pos, "damaged message_index record")
        elif parses(op):
            try:
                yield parse_record(op, buf[pos + RECORD_HEAD : end])
            except PARSE_ERRORS:
                yield Damage(pos, end - pos, f"damaged {Opcode(op).name.lower()} record")
        pos = end


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


__all__ = ["OVERRAN", "walk"]
