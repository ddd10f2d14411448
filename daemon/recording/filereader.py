"""Reading one recording file, trusting only what checks out, and saying what it lost.

The records come from :mod:`~loopcal.daemon.recording.mcap_records` (every length, offset and CRC
checked; the summary through :mod:`~loopcal.daemon.recording.mcap_summary`, the data section
record by record through :mod:`~loopcal.daemon.recording.walk`); this module turns them into
scan rows and events: each scan once (within a file a scan is its power-on epoch and
counter), the counter gaps no recorded ``missed`` explains reported as lost scans, and every
damaged part named (:class:`~loopcal.daemon.recording.recordingfile.RecordingFile`).

What a damaged file lost is counted from the file's own records: in a closed file, by its
statistics record (one ``/joint/state`` message per scan written, and the events), whose
CRC the summary's covers; in any file, placed by counter gaps and by the views of scans
whose raw chunk was lost (:mod:`~loopcal.daemon.recording.losses`); where neither can
count what a damaged part held (before the first scan known, or after the last, in a file
without trusted statistics), the count is given as "at least" and the place named.
"""

from __future__ import annotations

import gc
import json
import mmap
import os
import stat
from pathlib import Path
from typing import BinaryIO

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Channel, ChunkIndex, MessageIndex, Metadata, Statistics

from .. import scan_rows
from ..events import Event
from ..times import time_or
from .columns import decode_scan_messages
from .damage import Damage
from .errors import RecordingError
from .losses import losses, losses_within, view_keys
from .mcap_records import (
    MAGIC,
    PARSE_ERRORS,
    RECORD_HEAD,
    ChunkRecords,
    is_chunk_body,
    is_ours,
    parse_record,
    read_chunk,
    read_header,
    record_at,
)
from .mcap_summary import SummarySection, read_summary
from .names import NAME_RE
from .recordingfile import RecordingFile
from .schemas import (
    BLOCK_SPAN_NS,
    COLUMNS_SPAN_NS,
    READ_FORMATS,
    TOPIC_EVENTS,
    TOPIC_SCANS,
    TOPIC_STATE,
    format_words,
    our_channel_id,
)
from .walk import OVERRAN, walk

#: what :func:`~loopcal.daemon.recording.walk.walk` calls a file's damaged start
_NO_MAGIC = "no MCAP magic at the start"
#: what it calls a stretch of bytes that is no record (it may have held anything)
_STRETCHES = ("zeros where records should be", "no valid record", OVERRAN)


class FileReader:
    """Reads the scans, events and metadata of one file, trusting only what checks out.

    :func:`~loopcal.daemon.recording.reader.read_recordings` makes one per file; use that.

    Parameters
    ----------
    path : pathlib.Path
        The file.
    since : int or None
        Keep scans with ``since <= stamp_ns`` (ns since the Unix epoch; None: no start).
    until : int or None
        Keep scans with ``stamp_ns < until`` (None: no end).
    """

    def __init__(self, path: Path, since: int | None, until: int | None) -> None:
        self.path = path
        self.since, self.until = since, until
        self.metadata: dict[str, dict[str, str]] = {}
        self.channels: dict[int, Channel] = {}
        #: damaged parts of the data section, by offset
        self.damage: dict[int, Damage] = {}
        #: what is wrong with the summary or the index (no data lost with it)
        self.index_damage: list[Damage] = []
        #: the statistics record of a summary whose CRC matched
        self.statistics: Statistics | None = None
        #: the loopcal record's format, when it is not this loopcal's
        self.other_format: str | None = None
        self.ours = True
        self._messages: list[tuple[int, int, bytes]] = []  # (chunk offset, channel, data)
        # damaged chunk offset -> {channel id: messages it held (None: not counted)}, from the
        # message indexes after it or the chunk index
        self._held: dict[int, dict[int, int | None]] = {}
        self._no_messages: set[int] = set()  # offsets of damaged records that hold none
        self._index_chunks: set[int] = set()  # offsets of damaged chunks the index names

    # -------------------------------------------------------------- whole file

    def read(self) -> tuple[np.ndarray, RecordingFile, list[Event]]:
        """Read the file once, with memory bounded by its size at opening.

        A file that ends in MCAP magic (closed: nothing appends to it or cuts it any more)
        is mapped read-only, not copied; any other is read up to its size when opened.

        Returns
        -------
        rows : ndarray of SCAN_DTYPE, shape (n,)
            Its intact scans in the window, in (epoch, counter) order, each once.
        info : RecordingFile
            What it held and what could not be read.
        events : list of Event
            The events of the chunks it read, in file order, each once (not cut to the
            window: the caller does that).

        Raises
        ------
        RecordingError
            If the file cannot be read, is not a regular file, is not an MCAP file, is an
            MCAP file but not a loopcal recording, or has another format version.
        """
        try:
            with open(self.path, "rb") as f:
                st = os.fstat(f.fileno())
                if not stat.S_ISREG(st.st_mode):
                    raise RecordingError(f"{self.path}: not a regular file: a recording is a file")
                data = _contents(f, st.st_size)
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        try:
            buf = memoryview(data)
            try:
                return self._read_bytes(buf)
            finally:
                buf.release()
        finally:
            if isinstance(data, mmap.mmap):
                _unmap(data)

    def _read_bytes(self, buf: memoryview) -> tuple[np.ndarray, RecordingFile, list[Event]]:
        info = RecordingFile(self.path, complete=False)
        start = bytes(buf[:8])
        if not start:
            info.note = "empty file (created, nothing written)"
            return scan_rows.empty(), info, []
        if start != MAGIC:
            if MAGIC.startswith(start) and len(buf) < len(MAGIC):
                info.note = f"only {len(buf)} bytes (created, nothing written)"
                return scan_rows.empty(), info, []
            if NAME_RE.match(self.path.name) is None and not _has_intact_chunk(buf):
                raise RecordingError(f"{self.path}: not an MCAP file (no MCAP magic bytes)")
        self._read_records(buf, info)
        self._check_is_recording()
        rows, events, bad, info.last_scan_chunk = self._decode()
        info.bad_messages = bad
        info.metadata = self.metadata
        info.damage = self.index_damage + sorted(self.damage.values(), key=lambda d: d.offset)
        self._judge_format(rows, bad, info)
        unique, duplicates = _unique_scans(rows)
        self._account(buf, info, unique, events)
        windowed = self._window(rows)
        if windowed is rows:
            rows, info.duplicates = unique, duplicates
        else:
            rows, info.duplicates = _unique_scans(windowed)
        info.scans = len(rows)
        if len(rows):
            info.first_stamp_ns = int(rows["stamp_ns"][0])
            info.last_stamp_ns = int(rows["stamp_ns"][-1])
        return rows, info, events

    def _read_records(self, buf: memoryview, info: RecordingFile) -> None:
        """Through the summary's index if it checks out and matches the chunks, else record
        by record."""
        self.ours = is_ours(read_header(buf))
        summary, why = read_summary(buf, strict=self.ours)
        if summary is not None and (summary.chunk_indexes or summary.statistics is not None):
            self.statistics = summary.statistics
            info.complete = self._read_indexed(buf, summary)
            if not info.complete:
                info.note = ("closed, but its chunk index does not match the chunks: read "
                             "record by record")  # fmt: skip
            return
        self._read_stream(buf)
        info.note = (f"no summary ({why}): read record by record up to its last intact "
                     "chunk")  # fmt: skip
        if why not in ("no footer (the file was not closed)", "no summary section"):
            self.index_damage.append(Damage(len(buf), 0, f"index unusable ({why})"))

    def _check_is_recording(self) -> None:
        topics = {c.topic for c in self.channels.values()}
        if TOPIC_SCANS not in topics and "loopcal" not in self.metadata and not self._messages:
            if not self.ours or (not self.damage and self.channels):
                listed = ", ".join(sorted(topics)) or "none"
                raise RecordingError(
                    f"{self.path}: an MCAP file but not a loopcal recording: it has no "
                    f"{TOPIC_SCANS} channel (its topics: {listed})"
                )
        fmt = self.metadata.get("loopcal", {}).get("format")
        if fmt is not None and fmt not in READ_FORMATS:
            self.other_format = fmt  # judged once the scans are decoded (_judge_format)

    def _judge_format(self, rows: np.ndarray, bad: int, info: RecordingFile) -> None:
        """A ``format`` other than this loopcal's: another format, refused, unless every scan
        block decodes in this format's layout, when it is one damaged byte of an unchecked
        metadata record (7 of the 8 bits of "1" make another character), named as such."""
        fmt = self.other_format
        if fmt is None:
            return
        if not len(rows) or bad:
            raise RecordingError(f"{self.path}: {format_words(fmt)}")
        info.damage.append(Damage(0, 0, (
            f"its loopcal record says format {fmt!r}, but every scan block is in the layout "
            "of a format this loopcal reads: the record is damaged")))  # fmt: skip

    # -------------------------------------------------------------- records

    def _ids(self, *topics: str) -> set[int]:
        ids = {i for i, c in self.channels.items() if c.topic in topics}
        if not ids and self.ours and not self.channels:
            ids = {our_channel_id(t) for t in topics}
        return ids

    def _in_window(self, start: int, end: int) -> bool:
        if self.since is not None and end + BLOCK_SPAN_NS < self.since:
            return False
        # a block's scans lie before its log time: by a second as written, a minute packed
        return not (self.until is not None and start - COLUMNS_SPAN_NS >= self.until)

    def _take(self, got: ChunkRecords | Damage) -> None:
        if isinstance(got, Damage):
            old = self.damage.get(got.offset)
            if old is not None and old.what == _NO_MAGIC != got.what:  # what follows it too
                got = Damage(0, max(old.length, got.length), f"{old.what}, then {got.what}",
                             got.start_ns, got.end_ns)  # fmt: skip
                self.damage[0] = got
            self.damage.setdefault(got.offset, got)
            return
        for ch in got.channels:
            self.channels.setdefault(ch.id, ch)
        self._messages += [(got.offset, cid, data) for cid, _t, data in got.messages]

    def _read_metadata(self, buf: memoryview, summary: SummarySection) -> None:
        for idx in summary.metadata_indexes:
            at = record_at(buf, idx.offset, len(buf))
            if at is None or at[0] != Opcode.METADATA or idx.length != RECORD_HEAD + at[1]:
                self._no_messages.add(idx.offset)
                self.damage.setdefault(idx.offset, Damage(idx.offset, idx.length,
                                                          "no metadata where the index says"))
                continue
            try:
                rec = parse_record(Opcode.METADATA, buf[idx.offset + RECORD_HEAD :
                                                         idx.offset + idx.length])
            except PARSE_ERRORS:
                self._no_messages.add(idx.offset)
                self.damage.setdefault(idx.offset, Damage(idx.offset, idx.length,
                                                          "damaged metadata record"))
                continue
            self.metadata[rec.name] = dict(rec.metadata)

    def _read_indexed(self, buf: memoryview, summary: SummarySection) -> bool:
        """The chunks the index names that hold scans or events. Where one does not check
        out, the file is read record by record instead (every intact chunk, wherever it
        is); False if that found chunks the index does not describe (moved)."""
        self.channels = dict(summary.channels)
        self._read_metadata(buf, summary)
        wanted = self._ids(TOPIC_SCANS, TOPIC_EVENTS)
        damaged = False
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            offsets = ci.message_index_offsets
            if offsets and wanted.isdisjoint(offsets):
                continue
            if not self._in_window(ci.message_start_time, ci.message_end_time):
                continue
            got = read_chunk(buf, ci.chunk_start_offset, strict=self.ours, wanted=wanted,
                             expected_length=ci.chunk_length)  # fmt: skip
            if isinstance(got, Damage):
                damaged = True
                got = Damage(got.offset, got.length, got.what, ci.message_start_time,
                             ci.message_end_time)  # fmt: skip
                self._held[got.offset] = dict.fromkeys(offsets)
            elif (got.start_ns, got.end_ns) != (ci.message_start_time, ci.message_end_time):
                damaged = True  # another chunk than the index says
            self._take(got)
        return not (damaged and self._read_unindexed(buf, summary))

    def _read_unindexed(self, buf: memoryview, summary: SummarySection) -> bool:
        """A closed file with a chunk that is not what its index says: every intact chunk
        read wherever it is (chunks moved, or a torn one), the views included. Where no
        intact chunk is where the index says, the index's account of it (its time span)
        stands. Returns whether intact chunks were found that the index does not describe
        (the index does not match the chunks: that is said as damage, no scan lost)."""
        told = dict(self.damage)
        self.damage, self._messages, self._held = {}, [], {}
        found = self._read_stream(buf)
        by_offset = {ci.chunk_start_offset: ci for ci in summary.chunk_indexes}
        elsewhere = {(span, _length_at(buf, off)) for off, span in found.items()}
        for off, d in told.items():
            ci = by_offset.get(off)
            if ci is None:  # a metadata record: what the walk found there, if anything
                if off in self.damage:
                    self._no_messages.discard(off)
                self.damage.setdefault(off, d)
            elif ((ci.message_start_time, ci.message_end_time), ci.chunk_length) in elsewhere:
                continue  # the chunk it names is intact, elsewhere
            elif off not in found:
                self.damage[off] = d  # the index's account: a chunk, and its time span
                self._index_chunks.add(off)
        moved = sorted(off for off, span in found.items()
                       if not _described(buf, off, span, by_offset.get(off)))  # fmt: skip
        if moved:
            what = "the chunk index does not match the chunks (each intact chunk read where it is)"
            self.index_damage.append(Damage(moved[0], 0, what))
        return bool(moved)

    def _read_stream(self, buf: memoryview) -> dict[int, tuple[int, int]]:
        """Every chunk in file order (the message indexes after a chunk are not trusted to
        say what it holds: a flipped channel id there would hide scans; they only count
        what a damaged chunk held). Returns the intact chunks' offsets and time spans."""
        found: dict[int, tuple[int, int]] = {}
        after: int | None = None  # a damaged record whose message indexes may follow
        for rec in walk(buf, strict=self.ours, wanted=lambda: None):
            if isinstance(rec, MessageIndex):
                if after is not None:
                    self._held.setdefault(after, {})[rec.channel_id] = len(rec.records)
                continue
            if isinstance(rec, Damage) and after is not None:
                self._held.pop(after, None)  # its message indexes are not all there
            after = rec.offset if isinstance(rec, Damage) else None
            if isinstance(rec, ChunkRecords):
                found[rec.offset] = (rec.start_ns, rec.end_ns)
                if self._in_window(rec.start_ns, rec.end_ns):
                    self._take(rec)
                else:
                    self._take(ChunkRecords(rec.offset, rec.start_ns, rec.end_ns, rec.channels))
            elif isinstance(rec, Damage):
                self._take(rec)
            elif isinstance(rec, Metadata):
                self.metadata.setdefault(rec.name, dict(rec.metadata))
            elif isinstance(rec, Channel):
                self.channels.setdefault(rec.id, rec)
        return found

    def _decode(self) -> tuple[np.ndarray, list[Event], int, int]:
        """Scan rows, events, how many messages did not decode, and the offset of the last
        chunk that gave scans."""
        scans_ids = self._ids(TOPIC_SCANS)
        event_ids = self._ids(TOPIC_EVENTS)
        blocks: list[bytes] = []
        events: list[Event] = []
        bad = 0
        last_chunk = -1
        for offset, cid, data in self._messages:
            if cid in scans_ids:
                blocks.append(data)
                last_chunk = max(last_chunk, offset)
            elif cid in event_ids:
                try:
                    events.append(Event.from_json(json.loads(data)))
                except (ValueError, TypeError, KeyError, AttributeError, RecursionError):
                    bad += 1
        rows, bad_blocks = decode_scan_messages(blocks)
        bad += bad_blocks
        seen: set[tuple[int, str, str]] = set()
        unique = []
        for e in events:  # a chunk read twice repeats its events
            key = (e.stamp_ns, e.kind, e.message)
            if key not in seen:
                seen.add(key)
                unique.append(e)
        return rows, unique, bad, last_chunk

    def _window(self, rows: np.ndarray) -> np.ndarray:
        if self.since is None and self.until is None:
            return rows
        s = rows["stamp_ns"]
        mask = np.ones(len(rows), dtype=bool)
        if self.since is not None:
            mask &= s >= self.since
        if self.until is not None:
            mask &= s < self.until
        return rows[mask]

    # -------------------------------------------------------------- what was lost

    @property
    def _windowed(self) -> bool:
        return self.since is not None or self.until is not None

    def _account(
        self, buf: memoryview, info: RecordingFile, rows: np.ndarray, events: list[Event]
    ) -> None:
        """The scans and events lost: counted by the statistics record where it is trusted
        and the whole file was read, else placed by counter gaps and views, and where
        damage may have held more than that, said to be unknown.

        rows: every scan read (not cut to the window), in order, each once."""
        holders = [d for d in self.damage.values() if self._may_hold(buf, d)]
        expected = self._statistics_count(TOPIC_STATE)
        seen = None
        if holders or (expected is not None and expected != len(rows)):
            state = self._ids(TOPIC_STATE)
            seen = view_keys([d for _o, cid, d in self._messages if cid in state])
        if not len(rows) and (seen is None or not len(seen)):
            holders = list(self.damage.values())  # nothing read: any damage may have held all
        if self._windowed:
            info.lost = losses_within(rows, self.since, self.until, seen)
        else:
            info.lost = losses(rows, seen)
        if expected is not None:
            info.lost_unplaced = max(0, expected - len(rows) - info.lost_scans)
            if info.lost_unplaced and not holders and not self.index_damage:
                # every indexed chunk intact and no damage that may hold scans (a metadata
                # record holds none): the count, which no CRC covers, is wrong (ci51)
                record = self.metadata.get("loopcal", {}).get("views") == "dropped"
                info.damage.append(Damage(len(buf), 0, (
                    f"the {'loopcal' if record else 'statistics'} record counts "
                    f"{info.lost_unplaced} scan(s) more than the intact chunks hold (no "
                    "chunk is damaged: the count is wrong, no scan lost)")))  # fmt: skip
                info.lost_unplaced = 0
        else:
            info.lost_unknown = self._unknown_scans(holders, rows, seen)
        expected_events = self._statistics_count(TOPIC_EVENTS)
        if expected_events is not None:
            info.lost_events = max(0, expected_events - len(events))
        else:
            info.lost_events, info.lost_events_unknown = self._events_held(holders)

    def _statistics_count(self, topic: str) -> int | None:
        """Messages of ``topic`` in the whole file by its statistics record (None: not
        trusted, not our layout (raw scans and a view per scan), or only part of the file
        was read)."""
        if self.statistics is None or self._windowed:
            return None
        topics = {c.topic for c in self.channels.values()}
        if not {TOPIC_SCANS, TOPIC_STATE} <= topics:  # not our layout: one view per scan
            return None
        ids = self._ids(topic)
        counts = self.statistics.channel_message_counts
        n = sum(counts.get(i, 0) for i in ids)
        if topic == TOPIC_STATE and not n:
            # views dropped by compaction: the loopcal record counts the scans instead (a
            # damaged or missing record: nothing counts them)
            record = self.metadata.get("loopcal", {})
            if record.get("views") == "dropped" and record.get("scans", "").isdigit():
                return int(record["scans"])
            return None
        return n

    def _may_hold(self, buf: memoryview, d: Damage) -> bool:
        """Whether a damaged part may have held messages: a chunk (even one whose opcode
        was hit) or a stretch of bytes that is no record, not a damaged small record."""
        if d.offset in self._no_messages or d.offset >= len(buf) or d.what == _NO_MAGIC:
            return False
        if self._windowed and d.start_ns is not None and d.end_ns is not None:
            if not self._in_window(d.start_ns, d.end_ns):
                return False
        if d.offset in self._index_chunks or buf[d.offset] == Opcode.CHUNK:
            return True
        if any(w in d.what for w in _STRETCHES):
            return True
        if "cut off" in d.what and d.offset + d.length < len(buf):
            return True  # not the end: a length that overran good chunks, skipped to them
        at = record_at(buf, d.offset, len(buf))
        return at is not None and is_chunk_body(buf[d.offset + RECORD_HEAD :
                                                    d.offset + RECORD_HEAD + at[1]])  # fmt: skip

    def _unknown_scans(
        self, holders: list[Damage], rows: np.ndarray, seen: np.ndarray | None
    ) -> str:
        """Where damage may have held scans that no counter gap or view counts: before the
        first scan known or after the last ("" if nowhere)."""
        if not holders:
            return ""
        ids = self._ids(TOPIC_SCANS, TOPIC_STATE)
        offsets = np.fromiter((off for off, cid, _d in self._messages if cid in ids), np.int64)
        stamps = [rows["stamp_ns"]] + ([] if seen is None else [seen["stamp_ns"]])
        known = np.concatenate(stamps)
        if not len(offsets) or not len(known):
            return f"no scan could be read, how many are lost is unknown (damage at byte " \
                   f"{holders[0].offset})"  # fmt: skip
        lo, hi = int(offsets.min()), int(offsets.max())
        first, last = int(known.min()), int(known.max())
        before, after = [], []
        for d in holders:
            spanned = d.start_ns is not None and d.end_ns is not None
            if lo < d.offset < hi or (spanned and first <= d.start_ns and d.end_ns <= last):
                continue  # between scans known: counter gaps count what it held
            if (d.start_ns < first) if d.start_ns is not None else d.offset < lo:
                before.append(d)
            else:
                after.append(d)
        texts = []
        if before:
            texts.append(f"an unknown number before {time_or(first)} (damage at byte "
                         f"{before[0].offset})")  # fmt: skip
        if after:
            texts.append(f"the scans after {time_or(last)} are lost, how many is unknown "
                         f"(damage at byte {after[0].offset})")  # fmt: skip
        return ", ".join(texts)

    def _events_held(self, holders: list[Damage]) -> tuple[int, bool]:
        """Events the damaged parts held, by the message indexes after them; and whether
        any may have held events that nothing counts."""
        ids = self._ids(TOPIC_EVENTS)
        if not ids:  # no channel known to be the events': whatever the damage held
            return 0, bool(holders)
        n, unknown = 0, False
        for d in holders:
            held = self._held.get(d.offset)
            if held is None:
                unknown = True
                continue
            for cid in ids & held.keys():
                count = held[cid]
                unknown |= count is None
                n += count or 0
        return n, unknown


def _contents(f: BinaryIO, size: int) -> mmap.mmap | bytes:
    """A file's bytes: mapped read-only if it ends in MCAP magic (closed: never appended to
    or cut back again, so the mapping cannot lose pages under the reader), else read, at
    most the ``size`` it had when opened (a file being written may grow, or be cut back
    to its last durable flush)."""
    if size >= 2 * len(MAGIC):
        f.seek(size - len(MAGIC))
        if f.read(len(MAGIC)) == MAGIC:
            return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        f.seek(0)
    return f.read(size)


def _unmap(data: mmap.mmap) -> None:
    """Close a mapping; a view of it still alive (in a traceback) is let go first."""
    try:
        data.close()
    except BufferError:
        gc.collect()
        try:
            data.close()
        except BufferError:  # still referenced: unmapped when the last view goes
            pass


def _length_at(buf: memoryview, off: int) -> int:
    """The length (head included) of the record at ``off`` (0 if it does not fit)."""
    at = record_at(buf, off, len(buf))
    return 0 if at is None else RECORD_HEAD + at[1]


def _described(buf: memoryview, off: int, span: tuple[int, int], ci: ChunkIndex | None) -> bool:
    """Whether the chunk index entry ``ci`` describes the intact chunk at ``off``."""
    if ci is None or (ci.message_start_time, ci.message_end_time) != span:
        return False
    return _length_at(buf, off) == ci.chunk_length


def _has_intact_chunk(buf: memoryview) -> bool:
    """Whether a file without MCAP magic still holds a chunk that checks out (a damaged
    start), as opposed to bytes that were never a recording."""
    for rec in walk(buf, strict=False, wanted=lambda: set()):
        if isinstance(rec, ChunkRecords):
            return True
    return False


def _in_order(rows: np.ndarray) -> bool:
    e, c = rows["epoch"], rows["counter64"]
    return bool(np.all((e[1:] > e[:-1]) | ((e[1:] == e[:-1]) & (c[1:] > c[:-1]))))


def _unique_scans(rows: np.ndarray) -> tuple[np.ndarray, int]:
    """Rows in (epoch, counter64) order, each key once (the first kept); and how many
    repeats were dropped. Within a file a key names one scan."""
    if len(rows) < 2 or _in_order(rows):
        return rows, 0
    rows = rows[np.lexsort((rows["counter64"], rows["epoch"]))]
    e, c = rows["epoch"], rows["counter64"]
    keep = np.ones(len(rows), dtype=bool)
    keep[1:] = (e[1:] != e[:-1]) | (c[1:] != c[:-1])
    return rows[keep], int(len(rows) - keep.sum())


# RecordingFile lives in .recordingfile; importable from here as before
__all__ = ["FileReader", "RecordingFile"]
