"""The summary section of a closed file, trusted only when its CRC matches.

:func:`read_summary` gives the summary (channels, statistics, chunk and metadata indexes) of
a file whose footer is intact and whose summary's CRC matches: its chunk index is then what
the writer wrote when it closed the file. :func:`read_statistics` gives the statistics
record alone, through the summary offsets. Records are parsed by
:mod:`~loopcal.daemon.recording.mcap_records`.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, Footer, MetadataIndex, Statistics

from .mcap_records import (
    FOOTER_BYTES,
    MAGIC,
    PARSE_ERRORS,
    RECORD_HEAD,
    chunk_index,
    known_opcode,
    parse_record,
    record_at,
)


@dataclass
class SummarySection:
    """A summary section whose CRC matched."""

    channels: dict[int, Channel]
    statistics: Statistics | None
    chunk_indexes: list[ChunkIndex]
    metadata_indexes: list[MetadataIndex]


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
) -> tuple[SummarySection | None, str]:
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
    summary = SummarySection({}, None, [], [])
    pos = footer.summary_start - base
    while pos < fpos:
        at = record_at(buf, pos, fpos)
        if at is None or not known_opcode(at[0]):
            return None, f"damaged summary record at byte {base + pos}"
        op, length = at
        body = buf[pos + RECORD_HEAD : pos + RECORD_HEAD + length]
        try:
            rec = chunk_index(body) if op == Opcode.CHUNK_INDEX else parse_record(op, body)
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


__all__ = ["SummarySection", "read_statistics", "read_summary"]
