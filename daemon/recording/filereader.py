"""Reading one recording file, trusting only what checks out, and saying what it lost.

The records come from :mod:`~loopcal.daemon.recording.records` (every length, offset and CRC
checked); this module turns them into scan rows and events: each scan once (within a file a
scan is its power-on epoch and counter), the counter gaps no recorded ``missed`` explains
reported as lost scans, and every damaged part named (:class:`RecordingFile`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata

from .. import scans as scan_rows
from ..events import Event
from .cdr import decode_scan_blocks_checked
from .errors import RecordingError
from .names import NAME_RE
from .records import (
    MAGIC,
    PARSE_ERRORS,
    RECORD_HEAD,
    ChunkRecords,
    Damage,
    Summary,
    is_ours,
    parse_record,
    read_chunk,
    read_header,
    read_summary,
    record_at,
    walk,
)
from .schemas import (
    BLOCK_SPAN_NS,
    CHANNELS,
    FORMAT_VERSION,
    NS_PER_S,
    TOPIC_EVENTS,
    TOPIC_SCANS,
)


@dataclass(frozen=True)
class Loss:
    """Scans a file should hold and does not (a damaged or missing chunk).

    A counter gap between two of its scans that no recorded ``missed`` count explains.

    Attributes
    ----------
    epoch : int
        The power-on epoch of the scans.
    first : int
        ``counter64`` of the first missing scan.
    count : int
        How many scans are missing, >= 1.
    after_ns : int
        Stamp of the scan before the gap, ns since the Unix epoch.
    before_ns : int
        Stamp of the scan after the gap, ns since the Unix epoch.
    """

    epoch: int
    first: int
    count: int
    after_ns: int
    before_ns: int


@dataclass
class RecordingFile:
    """What one file of a recording held, and what of it could not be read.

    One per file in :attr:`Recording.files <loopcal.daemon.recording.reader.Recording.files>`.

    Attributes
    ----------
    path : pathlib.Path
        The file.
    complete : bool
        Closed normally (summary and index present and intact).
    scans : int, default 0
        Scans read from it: within the time window, each once, without those a file read
        before it already gave.
    first_stamp_ns : int or None, default None
        The first scan's stamp, ns since the Unix epoch (None: no scan).
    last_stamp_ns : int or None, default None
        The last scan's stamp, ns since the Unix epoch (None: no scan).
    metadata : dict of str to dict of str to str
        Metadata records by name (``loopcal``, ``device``, ``controller_config``), each
        ``{key: value}`` (docs/recording.md).
    note : str, default ""
        How the file was read when it was not closed normally (empty for a complete one).
    damage : list of Damage
        The parts that could not be trusted
        (:class:`~loopcal.daemon.recording.records.Damage`: byte ranges, what was wrong,
        the time span of the messages they held where known).
    lost : list of Loss
        Scans known to be missing from the file (counter gaps no ``missed`` explains).
    duplicates : int, default 0
        Scans that appeared more than once in the file (each is returned once).
    bad_messages : int, default 0
        Scan blocks or events inside intact chunks that did not decode.
    last_scan_chunk : int, default -1
        Byte offset of the last intact chunk that held scans (-1: none): damage after it
        cut the file's end off.
    """

    path: Path
    complete: bool
    scans: int = 0
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    note: str = ""
    damage: list[Damage] = field(default_factory=list)
    lost: list[Loss] = field(default_factory=list)
    duplicates: int = 0
    bad_messages: int = 0
    # byte offset of the last intact chunk that held scans (-1: none)
    last_scan_chunk: int = -1

    @property
    def lost_scans(self) -> int:
        """How many scans are known to be missing (the counts of :attr:`lost`, summed)."""
        return sum(x.count for x in self.lost)

    @property
    def intact(self) -> bool:
        """Whether the file read whole (nothing damaged, missing, duplicated or undecodable)."""
        return not (self.damage or self.lost or self.duplicates or self.bad_messages)

    @property
    def warning(self) -> str:
        """One line naming the file and what of it was lost, or ``""`` if it read intact.

        The scans missing (counters, epoch and UTC times of up to three gaps), the scans
        lost after damage at the end, damaged parts inside, duplicates dropped and
        undecodable messages, separated by ``;``.
        """
        if self.intact:
            return ""
        parts: list[str] = []
        if self.lost:
            spans = ", ".join(
                f"counters {x.first}-{x.first + x.count - 1} of epoch {x.epoch} "
                f"({utc_text(x.after_ns)} to {utc_text(x.before_ns)})"
                for x in self.lost[:3]
            )
            more = f" and {len(self.lost) - 3} more gap(s)" if len(self.lost) > 3 else ""
            parts.append(f"{self.lost_scans} scan(s) missing: {spans}{more}")
        tail = [d for d in self.damage if self._after_last_scan(d)]
        if tail:
            d = tail[0]
            span = ""
            if d.end_ns:
                span = f" (messages of {utc_text(d.start_ns)} to {utc_text(d.end_ns)})"
            parts.append(f"the scans after {utc_text(self.last_stamp_ns)} are lost: {d.what} at "
                         f"byte {d.offset}{span}" if self.last_stamp_ns is not None else
                         f"no scan could be read: {d.what} at byte {d.offset}{span}")  # fmt: skip
        inner = [d for d in self.damage if d not in tail]
        if inner:
            what = "; ".join(f"{d.what} at byte {d.offset}" for d in inner[:3])
            more = f"; {len(inner) - 3} more" if len(inner) > 3 else ""
            cost = "" if self.lost else " (no scan missing around them)"
            parts.append(f"{len(inner)} damaged part(s): {what}{more}{cost}")
        if self.duplicates:
            parts.append(f"{self.duplicates} duplicated scan(s) dropped (each kept once)")
        if self.bad_messages:
            parts.append(f"{self.bad_messages} undecodable message(s) skipped")
        return f"{self.path}: " + "; ".join(parts)

    def _after_last_scan(self, d: Damage) -> bool:
        return d.offset > self.last_scan_chunk


def utc_text(ns: int | None) -> str:
    """A time stamp for people: ``YYYY-mm-dd HH:MM:SS.ss UTC``.

    Parameters
    ----------
    ns : int or None
        ns since the Unix epoch.

    Returns
    -------
    str
        The UTC time to the hundredth of a second (truncated); ``"?"`` for None, and
        ``"N ns"`` for a time a datetime cannot hold.
    """
    if ns is None:
        return "?"
    sec, rest = divmod(int(ns), NS_PER_S)
    try:
        t = datetime.fromtimestamp(sec, UTC)
    except (OverflowError, OSError, ValueError):
        return f"{ns} ns"
    return f"{t:%Y-%m-%d %H:%M:%S}.{rest // 10_000_000:02d} UTC"


#: channel ids our writer gives the topics (in CHANNELS order, from 1), for a file of ours
#: whose channel records were lost with its first chunk
_OUR_CHANNEL_IDS = {topic: i for i, topic in enumerate(CHANNELS, start=1)}


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
        self.damage: dict[int, Damage] = {}
        self.ours = True
        self._messages: list[tuple[int, int, bytes]] = []  # (chunk offset, channel, data)

    # -------------------------------------------------------------- whole file

    def read(self) -> tuple[np.ndarray, RecordingFile, list[Event]]:
        """Read the file once.

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
            If the file cannot be read, is not an MCAP file, is an MCAP file but not a
            loopcal recording, or has another format version.
        """
        try:
            with open(self.path, "rb") as f:
                data = f.read()
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        info = RecordingFile(self.path, complete=False)
        if not data:
            info.note = "empty file (created, nothing written)"
            return scan_rows.empty(), info, []
        buf = memoryview(data)
        if not data.startswith(MAGIC):
            if MAGIC.startswith(data):
                info.note = f"only {len(data)} bytes (created, nothing written)"
                return scan_rows.empty(), info, []
            if NAME_RE.match(self.path.name) is None and not _has_intact_chunk(buf):
                raise RecordingError(f"{self.path}: not an MCAP file (no MCAP magic bytes)")
        header = read_header(buf)
        self.ours = is_ours(header)
        summary, why = read_summary(buf, strict=self.ours)
        if summary is not None and (summary.chunk_indexes or summary.statistics is not None):
            self._read_indexed(buf, summary)
            info.complete = True
        else:
            self._read_stream(buf)
            info.note = (f"no summary ({why}): read record by record up to its last intact "
                         "chunk")  # fmt: skip
            if why not in ("no footer (the file was not closed)", "no summary section"):
                info.damage.append(Damage(len(buf), 0, f"index unusable ({why})"))
        self._check_is_recording()
        rows, events, bad, info.last_scan_chunk = self._decode()
        info.bad_messages = bad
        info.metadata = self.metadata
        info.damage += sorted(self.damage.values(), key=lambda d: d.offset)
        windowed = self._window(rows)
        if windowed is rows:
            rows, info.duplicates = _unique_scans(rows)
            info.lost = _losses(rows)
        else:
            # a scan the file holds but stamped outside the window is not lost: the losses
            # are the file's own gaps between two scans the window keeps (in a recording
            # whose stamps went back, as older recorders' did at --speed 10, the window's
            # holes would otherwise read as scans missing)
            info.lost = losses_within(_unique_scans(rows)[0], self.since, self.until)
            rows, info.duplicates = _unique_scans(windowed)
        info.scans = len(rows)
        if len(rows):
            info.first_stamp_ns = int(rows["stamp_ns"][0])
            info.last_stamp_ns = int(rows["stamp_ns"][-1])
        return rows, info, events

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
        if fmt is not None and fmt != FORMAT_VERSION:
            raise RecordingError(
                f"{self.path}: recording format {fmt}, this loopcal reads format {FORMAT_VERSION}"
            )

    # -------------------------------------------------------------- records

    def _ids(self, *topics: str) -> set[int]:
        ids = {i for i, c in self.channels.items() if c.topic in topics}
        if not ids and self.ours and not self.channels:
            ids = {_OUR_CHANNEL_IDS[t] for t in topics}
        return ids

    def _in_window(self, start: int, end: int) -> bool:
        if self.since is not None and end + BLOCK_SPAN_NS < self.since:
            return False
        return not (self.until is not None and start >= self.until)

    def _take(self, got: ChunkRecords | Damage) -> None:
        if isinstance(got, Damage):
            self.damage.setdefault(got.offset, got)
            return
        for ch in got.channels:
            self.channels.setdefault(ch.id, ch)
        self._messages += [(got.offset, cid, data) for cid, _t, data in got.messages]

    def _read_indexed(self, buf: memoryview, summary: Summary) -> None:
        self.channels = dict(summary.channels)
        for idx in summary.metadata_indexes:
            at = record_at(buf, idx.offset, len(buf))
            if at is None or at[0] != Opcode.METADATA or idx.length != RECORD_HEAD + at[1]:
                self.damage.setdefault(idx.offset, Damage(idx.offset, idx.length,
                                                          "no metadata where the index says"))
                continue
            try:
                rec = parse_record(Opcode.METADATA, buf[idx.offset + RECORD_HEAD :
                                                         idx.offset + idx.length])
            except PARSE_ERRORS:
                self.damage.setdefault(idx.offset, Damage(idx.offset, idx.length,
                                                          "damaged metadata record"))
                continue
            self.metadata[rec.name] = dict(rec.metadata)
        wanted = self._ids(TOPIC_SCANS, TOPIC_EVENTS)
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            offsets = ci.message_index_offsets
            if offsets and wanted.isdisjoint(offsets):
                continue
            if not self._in_window(ci.message_start_time, ci.message_end_time):
                continue
            got = read_chunk(buf, ci.chunk_start_offset, strict=self.ours, wanted=wanted,
                             expected_length=ci.chunk_length)  # fmt: skip
            if isinstance(got, Damage) and got.end_ns is None:
                got = Damage(got.offset, got.length, got.what, ci.message_start_time,
                             ci.message_end_time)  # fmt: skip
            self._take(got)

    def _read_stream(self, buf: memoryview) -> None:
        """Every chunk in file order (the message indexes after a chunk are not trusted to
        say what it holds: a flipped channel id there would hide scans)."""
        for rec in walk(buf, strict=self.ours, wanted=lambda: None):
            if isinstance(rec, ChunkRecords):
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
        rows, bad_blocks = decode_scan_blocks_checked(blocks)
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


def losses_within(rows: np.ndarray, since: int | None, until: int | None) -> list[Loss]:
    """The losses of ``rows`` (:func:`_losses`) between two scans both stamped in
    ``since <= stamp < until``."""

    def inside(ns: int) -> bool:
        return (since is None or ns >= since) and (until is None or ns < until)

    return [x for x in _losses(rows) if inside(x.after_ns) and inside(x.before_ns)]


def _losses(rows: np.ndarray) -> list[Loss]:
    """Counter gaps between consecutive scans of a file that their ``missed`` counts do not
    explain: within an epoch, ``counter - previous - 1 > missed``; at a new epoch's first
    scan in the file, ``counter > missed``."""
    if len(rows) < 2:
        return []
    e, c, m = rows["epoch"], rows["counter64"], rows["missed"].astype(np.uint64)
    same = e[1:] == e[:-1]
    step = np.where(same, c[1:] - c[:-1] - np.uint64(1), c[1:])
    out = []
    for i in np.flatnonzero(step > m[1:]):
        first = int(c[i]) + 1 if same[i] else int(m[i + 1])
        out.append(Loss(int(e[i + 1]), first, int(step[i] - m[i + 1]),
                        int(rows["stamp_ns"][i]), int(rows["stamp_ns"][i + 1])))  # fmt: skip
    return out
