"""Compacting a closed recording: the same records in chunks of a minute instead of two per
second.

While a file is written, every flush (about once a second) closes two small chunks, so that
a crash loses at most that second; a day is 86,400 of them, and reading spends its time per
chunk. Once a file is closed (rotated), nothing will be appended to it, and it can be
rewritten for reading: the raw scans and events in chunks of at most :data:`CHUNK_SPAN_NS`
(60 s) of scan time, each followed by a chunk of the per-scan views of the same minute (so a
reader of the scans still skips them), the same channels with the same ids, the same
metadata (the ``loopcal`` record gains ``compacted_utc`` and ``chunk_span_s``). Every reader
reads it as before (ours, Python ``mcap``, Foxglove's).

Why a minute, not a few MiB: a chunk is the unit of damage (one CRC over it: one flipped bit
and the reader drops the chunk whole), so the chunk's span is what one damaged byte costs.
Chunks of 4 MiB held a whole hour's scans and lost them all to one bit; a minute's chunks
lose at most a minute, and a day's scans are 1,440 chunks, still few enough to read in under a
second. The views' chunk of each minute lies between two scans' chunks, so a run of zeros
shorter than it (a torn sector, a 4 KiB page) cannot reach two minutes of scans.
(``bench/fuzz_compacted.py`` measures both layouts.)

Nothing can be lost doing it: the new version goes to a temporary file beside the original
(``.NAME.compact.tmp``), is checked record by record by
:func:`~loopcal.daemon.recording.verify.verify_file` (what ``loopcal verify`` runs), read back
with :func:`~loopcal.daemon.recording.read_recordings` and compared scan for scan and event for
event with the original, and message count for message count with the original's own
statistics record (every chunk's CRC checked as it is copied: the mcap library would skip a
chunk it cannot read, or copy a corrupted one, without a word), fsynced, and only then
renamed over it (atomic), and the directory fsynced. A file that is
not closed, has any record that does not check out, or is already compact is left as it
is (already compact is told from its metadata record alone, without reading its chunks; a
file compacted by an older loopcal into chunks of 4 MiB, whose record has no
``chunk_span_s``, is compacted again, into chunks of a minute).
Killed at any step, the original is there, whole, or the compacted copy is; a temporary
file left behind is removed by the next compaction of the directory.

Older files can leave their views out (``drop_views``, ``loopcal compact --drop-views``, the
daemon past ``[recording].keep_views_days``): the same rewrite without ``/joint/state`` and
``/plate/transform``, nine tenths of a compacted file, which ``loopcal export`` makes again
from the raw scans; the ``loopcal`` record then counts the file's scans, for the reader to
count losses against (docs/recording.md, "Views in older files").

Two compactions at once (two ``loopcal compact`` on one directory, or one beside the
daemon's compactor) never touch each other's work: a compaction holds an advisory lock
(``flock``) on the original from before its temporary file exists until it is renamed, a
second one of the same file finds the lock taken and leaves the file to it, and a
temporary file is removed as stale only while its original's lock can be had (its writer
is gone). The last step, checking that the original is still the file that was read and
renaming the copy over it, holds a lock on the directory (:func:`directory_lock`) that the
recorder's retention holds too while it deletes a file, so a file deleted to keep the disk
budget never comes back as its compacted copy, whichever process compacts it.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer
from numpy.lib.recfunctions import repack_fields

from ..config import durable
from ..times import now_text
from .columns import decode_columns, decode_scan_messages, encode_columns, is_columns
from .errors import RecordingError
from .mcap_records import MAGIC
from .names import find_recordings, recording_paths
from .reader import read_recordings
from .schemas import (
    BLOCK_SPAN_NS,
    COMPACT_FORMAT,
    NS_PER_S,
    SCAN_COLUMNS_SCHEMA,
    TOPIC_EVENTS,
    TOPIC_LOG,
    TOPIC_SCANS,
    TOPIC_STATE,
    TOPIC_TRANSFORM,
    schema_bytes,
)
from .verify import verify_file

log = logging.getLogger(__name__)

#: the longest span of time one chunk of a compacted file holds, ns: from its first scan to
#: the end of its last (a block's scans lie within BLOCK_SPAN_NS of its log time), and from
#: its first message to its last; a damaged chunk costs at most this much of the recording
CHUNK_SPAN_NS = 60 * NS_PER_S
#: uncompressed bytes per chunk at most, whatever its span (a minute of scans at 20 Hz is
#: about 70 KB: this bounds a module scanning much faster; a reader decompresses a chunk whole)
CHUNK_BYTES = 4 << 20
#: the topics whose messages a reader of the scans needs (the rest are views)
_RAW_TOPICS = (TOPIC_SCANS, TOPIC_EVENTS, TOPIC_LOG)
#: the per-scan views a compaction with ``drop_views`` leaves out (``loopcal export`` makes
#: them again from the scans and the file's controller config); the scene, one message a
#: file, stays
DROPPED_VIEWS = (TOPIC_STATE, TOPIC_TRANSFORM)


@dataclass(frozen=True)
class Compacted:
    """What :func:`compact` did: ``done`` (the file was rewritten) or why not (``failed``:
    because of something wrong with the file or its copy, not because it needs no
    compaction; ``not_recording``, with ``failed``: the file is not a recording this
    loopcal reads, the reader's RecordingError in ``reason``); the chunk counts and sizes
    before and after."""

    path: Path
    done: bool
    reason: str = ""
    chunks_before: int = 0
    chunks_after: int = 0
    bytes_before: int = 0
    bytes_after: int = 0
    failed: bool = False
    not_recording: bool = False


def refuse_non_recording(path: Path) -> None:
    """Raise :class:`RecordingError`, saying why, if ``path`` is plainly not a recording:
    not a regular file (told without blocking on a FIFO), or bytes without MCAP's magic that
    the reader refuses (``/etc/passwd``). Cheap: a file that starts like MCAP (or is
    empty, or holds only the start of the magic: a recording just created) is left to
    :func:`compact` to judge, and only a file without the magic is read whole."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror or exc}") from None
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise RecordingError(f"{path}: not a regular file: a recording is a file")
        head = os.read(fd, len(MAGIC))
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if not MAGIC.startswith(head) and not head.startswith(MAGIC):
        read_recordings(path)  # raises unless it is a recording whose start was damaged


def recordings_named(paths: list[Path]) -> list[Path]:
    """The recording files ``paths`` name (files, and directories of them), each plainly
    bad one refused first (:class:`RecordingError`, naming it: see
    :func:`refuse_non_recording`; a directory without recordings), before any is touched."""
    files = recording_paths(paths)
    for p in paths:
        if p.is_dir():
            if not find_recordings(p):
                raise RecordingError(f"{p}: no recordings (loopcal-*.mcap) in this directory")
        else:
            refuse_non_recording(p)
    return files


def _tmp_of(path: Path) -> Path:
    return path.with_name(f".{path.name}.compact.tmp")


@contextlib.contextmanager
def _compacting(path: Path):
    """Hold the compaction lock of ``path`` (``flock`` on the original); yields False, and
    holds nothing, when another process holds it. A missing original yields True (its
    temporary, if any, has no writer left)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # a FIFO: no wait
    except FileNotFoundError:
        yield True
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        yield True
    finally:
        os.close(fd)  # releases the lock


@contextlib.contextmanager
def directory_lock(directory: Path):
    """Hold the advisory lock (``flock``) of a recording directory: while a compaction
    checks and replaces a file, and while the retention deletes one. Blocks until it is had
    (each holder keeps it for one ``stat`` and one rename or unlink)."""
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


def remove_stale_temporaries(directory: Path) -> None:
    """Remove the temporary files (:func:`_tmp_of`) that killed compactions left in a
    directory, never one whose compaction is still running; call it before any compaction
    there."""
    for tmp in Path(directory).glob(".loopcal-*.mcap.compact.tmp"):
        original = tmp.with_name(tmp.name.removeprefix(".").removesuffix(".compact.tmp"))
        with _compacting(original) as ours:
            if ours:
                tmp.unlink(missing_ok=True)


def compact(path: Path, *, drop_views: bool = False) -> Compacted:
    """Rewrite the closed recording ``path`` in chunks of a minute, verified, atomically (see the
    module docstring). Raises OSError if the disk refuses (the original is then as it was).

    drop_views: leave out the per-scan views (:data:`DROPPED_VIEWS`), about nine tenths of a
    compacted file: what is left is the raw scans, the events, the scene and the metadata,
    the ``loopcal`` record saying ``views = "dropped"`` and how many scans the file holds
    (``scans``, which a reader counts lost scans against, as it counts them against the
    views otherwise). A compact file that still has its views is rewritten without them.
    The original is checked to be the file that was read (not deleted or replaced
    meanwhile) and replaced under :func:`directory_lock`."""
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        return Compacted(path, False, "deleted before it was compacted")
    if not stat.S_ISREG(mode):  # a FIFO would block the reader, a device never end
        return Compacted(path, False, f"{path}: not a regular file: a recording is a file",
                         failed=True, not_recording=True)  # fmt: skip
    if _says_compacted(path, drop_views):
        return Compacted(path, False, "already compact")
    with _compacting(path) as ours:
        if not ours:
            return Compacted(path, False, "being compacted by another process")
        return _compact_locked(path, drop_views)


def _compact_locked(path: Path, drop_views: bool) -> Compacted:
    try:
        original = read_recordings(path)
    except RecordingError as exc:
        if not path.exists():  # the retention's, say: nothing wrong with the file
            return Compacted(path, False, "deleted before it was compacted")
        return Compacted(path, False, str(exc), failed=True, not_recording=True)
    info = original.files[0]
    if not info.intact:
        return Compacted(path, False, "damaged: left as it is", failed=True)
    if not info.complete:
        return Compacted(path, False, "not closed: left as it is")
    if _compact_enough(info.metadata.get("loopcal", {}), drop_views):
        return Compacted(path, False, "already compact")
    before = path.stat()
    size = before.st_size
    tmp = _tmp_of(path)
    tmp.unlink(missing_ok=True)
    try:
        try:
            chunks_before, counts = _rewrite(path, tmp, len(original.scans) if drop_views
                                             else None)  # fmt: skip
        except _Damaged as exc:
            tmp.unlink(missing_ok=True)
            log.error("not compacting %s: damaged: %s; left as it is", path, exc)
            return Compacted(path, False, f"damaged: {exc}: left as it is", failed=True)
        durable.step("compact-written")
        chunks_after, problem = _verify(tmp, original, counts, drop_views)
        if problem:
            tmp.unlink(missing_ok=True)
            log.error("compacting %s: %s; the original is kept", path, problem)
            return Compacted(path, False, f"verification failed: {problem}", failed=True)
        durable.step("compact-verified")
        with directory_lock(path.parent):
            try:
                now = path.stat()
            except FileNotFoundError:
                now = None
            if now is None or (now.st_ino, now.st_size) != (before.st_ino, before.st_size):
                tmp.unlink(missing_ok=True)
                return Compacted(path, False, "deleted or replaced while it was compacted")
            os.replace(tmp, path)
        durable.step("compact-renamed")
        durable.fsync_dir(path.parent)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return Compacted(path, True, "", chunks_before, chunks_after, size, path.stat().st_size)


def _says_compacted(path: Path, drop_views: bool = False) -> bool:
    """Whether a closed file's ``loopcal`` metadata record says it was compacted (with this
    loopcal's format, and without its views if ``drop_views``), read through the summary's
    metadata index: the footer, the summary and one small record, no chunk. False whenever
    that cannot be told so cheaply (no summary, anything unreadable): the file is then read
    whole and judged as before. A file this finds compact is left alone without that read,
    damaged or not."""
    try:
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None or not (summary.chunk_indexes or summary.statistics):
                return False  # read_recordings reads it as not closed
            record: dict[str, str] = {}
            for m in reader.iter_metadata():
                if m.name == "loopcal":
                    record = dict(m.metadata)  # the last one, as read_recordings keeps it
    except Exception:  # noqa: BLE001 - any damage: the careful read below decides
        return False
    return _compact_enough(record, drop_views)


def _compact_enough(record: dict[str, str], drop_views: bool = False) -> bool:
    """Whether a ``loopcal`` metadata record says its file was compacted into chunks of at
    most :data:`CHUNK_SPAN_NS` (an older loopcal's compaction, into chunks of 4 MiB that
    held an hour, did not write ``chunk_span_s``: such a file is compacted again), and
    without its views if ``drop_views``."""
    if "compacted_utc" not in record or record.get("format") != COMPACT_FORMAT:
        return False  # not compacted, or compacted before the scans were packed in columns
    if drop_views and record.get("views") != "dropped":
        return False
    try:
        return int(record.get("chunk_span_s", "")) * NS_PER_S <= CHUNK_SPAN_NS
    except ValueError:
        return False


class _Damaged(Exception):
    """The original holds a record that does not check out (a chunk's CRC, a message the
    library could not read, fewer messages than its statistics record)."""


def _rewrite(path: Path, tmp: Path, scans_if_dropping: int | None) -> tuple[int, dict[str, int]]:
    """Write the compacted copy; returns the original's chunk count and its message count
    per topic as its own statistics record them. Raises :class:`_Damaged` when the
    original's messages do not all read back (checked against those statistics, every
    chunk's CRC validated: the library skips what it cannot read without a word).

    scans_if_dropping: the original's scan count, to leave the views out (None: keep them)."""
    with open(path, "rb") as src:
        reader = make_reader(src, validate_crcs=True)
        header = reader.get_header()
        summary = reader.get_summary()
        assert summary is not None  # a closed, intact file (checked by the caller)
        if summary.statistics is None:
            raise _Damaged("no statistics record to check its messages against")
        recorded = {k: v for k, v in summary.statistics.channel_message_counts.items() if v}
        metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC,
                     os.stat(path).st_mode & 0o7777)  # fmt: skip
        with os.fdopen(fd, "wb") as out:
            w = Writer(out, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD,
                       enable_crcs=True)  # fmt: skip
            w.start(profile=header.profile, library=header.library)
            schema_ids = {}
            for sid in sorted(summary.schemas):
                s = summary.schemas[sid]
                schema_ids[sid] = w.register_schema(s.name, s.encoding, s.data)
            columns_sid = w.register_schema(SCAN_COLUMNS_SCHEMA, "ros2msg",
                                            schema_bytes(SCAN_COLUMNS_SCHEMA))  # fmt: skip
            for cid in sorted(summary.channels):
                c = summary.channels[cid]
                sid = columns_sid if c.topic == TOPIC_SCANS else schema_ids.get(c.schema_id, 0)
                new = w.register_channel(c.topic, c.message_encoding, sid, dict(c.metadata))
                if new != cid:  # our writer numbers channels from 1 in order: so does this one
                    raise RecordingError(f"{path}: channel ids are not consecutive")
            stamp = now_text()
            span_s = str(CHUNK_SPAN_NS // NS_PER_S)
            for name, record in metadata:
                if name == "loopcal":
                    record = {**record, "format": COMPACT_FORMAT, "compacted_utc": stamp,
                              "chunk_span_s": span_s}  # fmt: skip
                    if scans_if_dropping is not None:
                        record.update(views="dropped", views_dropped_utc=stamp,
                                      scans=str(scans_if_dropping))  # fmt: skip
                w.add_metadata(name, record)
            raw = {cid for cid, c in summary.channels.items() if c.topic in _RAW_TOPICS}
            scans = {cid for cid, c in summary.channels.items() if c.topic == TOPIC_SCANS}
            dropped = set()
            if scans_if_dropping is not None:
                dropped = {cid for cid, c in summary.channels.items() if c.topic in DROPPED_VIEWS}
            pair = _ChunkPair(w, scans)
            counts: dict[int, int] = {}
            try:
                # every message once, in file order (the original's raw chunk of a second,
                # then its views' chunk): each minute's raw messages into one chunk, its
                # views into the next
                for _, channel, message in reader.iter_messages(log_time_order=False):
                    cid = channel.id
                    counts[cid] = counts.get(cid, 0) + 1
                    if cid in dropped:
                        continue
                    t = message.log_time
                    m = (cid, t, message.data, message.publish_time, message.sequence)
                    pair.add(cid in raw, m, _scan_span(message.data, t) if cid in scans
                             else (t, t))  # fmt: skip
            except OSError:
                raise
            except Exception as exc:  # noqa: BLE001 - any record that does not check out
                raise _Damaged(f"{type(exc).__name__}: {exc}") from None
            pair.write()
            if counts != recorded:
                lost = {summary.channels[c].topic: recorded[c] - counts.get(c, 0)
                        for c in recorded if counts.get(c, 0) != recorded[c]}  # fmt: skip
                raise _Damaged("messages its statistics record do not read back: " + ", ".join(
                    f"{topic} {n:+d}" for topic, n in lost.items()))  # fmt: skip
            w.finish()
            out.flush()
            os.fsync(out.fileno())
    return len(summary.chunk_indexes), {summary.channels[c].topic: n for c, n in recorded.items()}


class _ChunkPair:
    """The messages of the chunks being gathered, raw (scans, events) and views, each group
    within :data:`CHUNK_SPAN_NS` of scan time (from the earliest time a message holds to the
    latest: see :func:`_scan_span`); written as a raw chunk then a views chunk whenever a
    message would stretch either group beyond it."""

    def __init__(self, writer: Writer, scans: set[int]) -> None:
        self.writer = writer
        self.scans = scans
        self.parts: dict[bool, list[tuple[int, int, bytes, int, int]]] = {True: [], False: []}
        self.spans: dict[bool, tuple[int, int] | None] = {True: None, False: None}

    def add(self, raw: bool, message: tuple[int, int, bytes, int, int],
            span: tuple[int, int]) -> None:  # fmt: skip
        """Add a message (channel id, log time, data, publish time, sequence), a raw one
        when ``raw``, holding scan time ``span`` (first, last) ns."""
        have = self.spans[raw]
        grown = span if have is None else (min(have[0], span[0]), max(have[1], span[1]))
        if have is not None and grown[1] - grown[0] > CHUNK_SPAN_NS:
            self.write()
            grown = span
        self.spans[raw] = grown
        self.parts[raw].append(message)

    def write(self) -> None:
        """Write what was gathered: the raw chunk (its scan blocks packed into one block of
        columns, logged at the last one's time, then the events), then the views' (the
        writer also closes a chunk at CHUNK_BYTES)."""
        for raw in (True, False):
            parts = self.parts[raw]
            if raw:
                parts = self._pack(parts)
            for cid, log_time, data, publish_time, sequence in parts:
                self.writer.add_message(cid, log_time, data, publish_time, sequence)
            self.writer.flush()
            self.parts[raw] = []
            self.spans[raw] = None


    def _pack(self, parts: list[tuple[int, int, bytes, int, int]]) -> list:
        blocks = [m for m in parts if m[0] in self.scans]
        if not blocks:
            return parts
        rows, bad = decode_scan_messages([m[2] for m in blocks])
        if bad:
            raise _Damaged(f"{bad} scan block(s) that do not decode")
        cid, log_time, _, publish_time, _ = blocks[-1]
        packed = (cid, log_time, encode_columns(rows), publish_time, blocks[0][4])
        return [packed, *(m for m in parts if m[0] not in self.scans)]


def _verify(tmp: Path, original, counts: dict[str, int], drop_views: bool) -> tuple[int, str]:
    """(chunks of the copy, "" or what differs from the original; with ``drop_views``, the
    copy must hold none of the views it leaves out and say how many scans it holds).

    counts: the original's messages per topic, by its statistics record."""
    checked = verify_file(tmp)
    if not checked.ok:
        return 0, f"the copy does not verify: {checked.damaged[0].text()}"
    if not checked.closed:
        return 0, "the copy was not closed"
    copy = read_recordings(tmp)
    f = copy.files[0]
    if not f.complete or not f.intact:
        return 0, "the copy does not read back intact"
    a, b = repack_fields(original.scans), repack_fields(copy.scans)
    if len(a) != len(b) or a.tobytes() != b.tobytes():
        return 0, f"the copy holds {len(b)} scans, not the original's {len(a)} exactly"
    if [e.to_json() for e in copy.events] != [e.to_json() for e in original.events]:
        return 0, "the copy's events differ"
    if drop_views and f.metadata.get("loopcal", {}).get("scans") != str(len(b)):
        return 0, "the copy's loopcal record does not count its scans"
    # against the original's statistics (its scan blocks are packed: compared scan by scan)
    left_out = {TOPIC_SCANS, *(DROPPED_VIEWS if drop_views else ())}
    want = {t: n for t, n in counts.items() if t not in left_out}
    got = {t: n for t, n in checked.messages.items() if n and t != TOPIC_SCANS}
    if got != want:
        return 0, f"message counts differ: {got} against the original's {counts}"
    for start_ns, end_ns, topics in checked.chunk_spans:
        span = _chunk_span(start_ns, end_ns, TOPIC_SCANS in topics)
        if span > CHUNK_SPAN_NS:
            return 0, f"a chunk spans {span / NS_PER_S:.1f} s, over {CHUNK_SPAN_NS / NS_PER_S} s"
    return checked.chunks, ""


def _scan_span(data: bytes, log_time: int) -> tuple[int, int]:
    """The scan time a ``/daq/scans`` message holds, ns: a block as written lies within
    BLOCK_SPAN_NS of its log time; a block of columns (a file compacted before) is decoded
    for its first and last stamps (it may start up to a minute before its log time)."""
    if is_columns(data):
        try:
            stamps = decode_columns(data)["stamp_ns"]
        except Exception as exc:  # noqa: BLE001 - any damage: the file is left as it is
            raise _Damaged(f"a block of columns that does not decode: {exc}") from None
        if len(stamps):
            return min(int(stamps[0]), log_time), max(int(stamps[-1]), log_time)
    return log_time, log_time + BLOCK_SPAN_NS


def _chunk_span(first_ns: int, last_ns: int, scans: bool) -> int:
    """The time a chunk holds, ns, from its first message's log time to its last's, and to
    the end of its last block's scans if it holds scans (a block's scans lie within
    BLOCK_SPAN_NS of its log time)."""
    return last_ns - first_ns + (BLOCK_SPAN_NS if scans else 0)


__all__ = [
    "CHUNK_BYTES",
    "CHUNK_SPAN_NS",
    "Compacted",
    "compact",
    "recordings_named",
    "refuse_non_recording",
    "remove_stale_temporaries",
]
