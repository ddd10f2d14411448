"""The recorder's writer thread: scans from the queue into rotating recording files.

Every flush period it writes what waited to the current file
(:class:`loopcal.daemon.recording.RecordingWriter`) and fsyncs; it rotates files by age, size,
reload and device change, and where the stamps go back (the host's clock was set back:
within a file time never goes back), deletes the oldest recordings to stay under the disk
budget, and rides out disk errors: the scans stay in memory (up to ``max_backlog_scans``),
it retries every few seconds, and writes them all once the disk takes them again.

What it shares with the other threads is explicit: the :class:`ScanQueue` the acquisition
fills, and the :class:`Shared` state (settings and controller config in force, the
recorder's own events and the count of every event recorded, whether a new file was asked
for) behind one lock.
"""

from __future__ import annotations

import collections
import errno
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import durable
from ..config.controller import ControllerConfig
from ..events import Event, Level
from ..recording import RecordingWriter, find_recordings, metadata_records, recording_name
from ..recording.compact import directory_lock
from ..recording.views import WrittenViews
from ..scan_rows import SCAN_DTYPE
from .acquisition import Batch, DeviceInfo
from .compactor import Compactor
from .settings import RecorderSettings, SettingsError

log = logging.getLogger(__name__)

DISK_RETRY_S = 5.0  # how often to try again while the disk refuses to write
RETENTION_CHECK_S = 30.0
MAX_PENDING_EVENTS = 1000
BACKLOG_PIECE_NS = 10_000_000_000  # a backlog is written and made durable 10 s at a time
STILL_FAILING_LOG_S = 60.0


#: errors that no retry will cure: the directory is wrong, not the disk momentarily full
_FATAL_DIR_ERRNOS = {errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EEXIST,
                     errno.ELOOP, errno.ENAMETOOLONG, errno.EISDIR}  # fmt: skip


def prepare_directory(directory: Path) -> None:
    """Create the recording directory if needed and check that a file can be created in it.

    Raises SettingsError (naming ``[recording].directory``) when it cannot be created or
    written for a reason retrying will not cure (permissions, a read-only file system, a
    file in the way). A full or failing disk is not refused here: the writer keeps the
    scans in memory and retries (a ``disk_error`` event).
    """

    def refuse(what: str, exc: OSError | None = None) -> SettingsError:
        why = f": {exc.strerror or exc}" if exc is not None else ""
        return SettingsError(f"{directory}: {what}{why}", "directory")

    try:
        durable.make_dirs(directory)  # a power cut after the first file leaves it there
    except FileExistsError:
        raise refuse("exists and is not a directory") from None
    except OSError as exc:
        if exc.errno in _FATAL_DIR_ERRNOS:
            raise refuse("cannot create the recording directory", exc) from None
        return
    if not directory.is_dir():
        raise refuse("exists and is not a directory")
    probe = directory / f".loopcal-write-test.{os.getpid()}"
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
    except FileExistsError:
        return
    except OSError as exc:
        if exc.errno in _FATAL_DIR_ERRNOS:
            raise refuse("cannot write in the recording directory", exc) from None
        return
    os.close(fd)
    probe.unlink(missing_ok=True)


class ScanQueue:
    """Batches from the acquisition thread to the writer thread; ``put`` never blocks.

    If the writer is stuck (a stalled disk) and more than ``cap`` scans wait, the oldest
    are dropped and counted in :attr:`dropped`, so memory stays bounded.
    """

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self._items: collections.deque[Batch] = collections.deque()
        self._scans = 0
        self._cond = threading.Condition()
        self.dropped = 0

    def put(self, batch: Batch) -> None:
        with self._cond:
            self._items.append(batch)
            self._scans += len(batch.rows)
            while self._scans > self.cap and len(self._items) > 1:
                old = self._items.popleft()
                self._scans -= len(old.rows)
                self.dropped += len(old.rows)
                if old.events:  # keep the events, drop the scans
                    self._items.appendleft(Batch(old.rows[:0], old.events, old.device))
            self._cond.notify()

    def get_all(self, timeout: float) -> list[Batch]:
        """Everything waiting, after waiting up to ``timeout`` s for something."""
        with self._cond:
            if not self._items and timeout > 0:
                self._cond.wait(timeout)
            items = list(self._items)
            self._items.clear()
            self._scans = 0
            return items

    def wake(self) -> None:
        with self._cond:
            self._cond.notify()


@dataclass
class RecorderStatus:
    """What the status line shows (written by the writer thread)."""

    file: Path | None = None
    files_written: int = 0
    scans_written: int = 0
    bytes_written: int = 0
    disk_error: str = ""
    backlog: int = 0
    #: the stamp of the newest scan written and made durable (None before the first)
    written_through_ns: int | None = None


@dataclass
class Shared:
    """What the recorder's threads share, behind :attr:`lock`: the settings and controller
    config in force, the recorder's own events waiting for the next flush, how many events
    of each (kind, level) were recorded (the metrics), and whether a new file was asked for
    (a reload)."""

    settings: RecorderSettings
    controller: ControllerConfig
    lock: threading.Lock = field(default_factory=threading.Lock)
    events: list[Event] = field(default_factory=list)
    rotate: bool = False
    counts: Counter[tuple[str, str]] = field(default_factory=Counter)

    def record(self, event: Event, *, pending: bool = True) -> None:
        """Count ``event`` as recorded (:meth:`event_counts`); ``pending``: also keep it
        for the writer's next flush (False: it reaches the file by another way, a batch of
        the acquisition or the writer's own list). Every event recorded goes through here."""
        with self.lock:
            if pending:
                self.events.append(event)
            self.counts[event.kind, event.level.name.lower()] += 1

    def event_counts(self) -> Counter[tuple[str, str]]:
        """How many events of each (kind, level) have been recorded so far."""
        with self.lock:
            return Counter(self.counts)

    def take_events(self) -> list[Event]:
        with self.lock:
            events, self.events = self.events, []
        return events

    def take_rotation(self) -> ControllerConfig:
        """The controller config a new file is to record; a new file asked for is so taken
        (the request is consumed)."""
        with self.lock:
            self.rotate = False
            return self.controller


class FileWriter:
    """The writer thread's state: pending scans, the current file, disk errors.

    queue: where the acquisition puts its batches. shared: the state the recorder's threads
    share. status: what the status line shows (written here). command: how the recorder
    was started (every file's metadata). done: set when the recorder stops: write
    everything, close the file, return from :meth:`run`. on_views: given every write's views
    as the file got them (:class:`~loopcal.daemon.recording.views.WrittenViews`; the live
    view), from this thread: it must return at once.
    """

    def __init__(self, queue: ScanQueue, shared: Shared, status: RecorderStatus, *,
                 command: str, done: threading.Event, compactor: Compactor | None = None,
                 on_views: Callable[[WrittenViews], None] | None = None) -> None:  # fmt: skip
        self.queue, self.shared, self.status = queue, shared, status
        self.command, self.done = command, done
        self.compactor = compactor
        self.on_views = on_views
        self.rows: list[np.ndarray] = []
        self.n_rows = 0
        self.events: list[Event] = []
        self.file: RecordingWriter | None = None
        self.file_opened = 0.0
        self.device: DeviceInfo | None = None
        self.file_device: DeviceInfo | None = None
        self.disk_error_since: float | None = None
        self.failing_logged = 0.0
        self.retry_at = 0.0
        self.next_retention = 0.0
        self.views_reported: Path | None = None

    def run(self) -> None:
        period = self.shared.settings.flush_period_s
        next_flush = time.monotonic() + period
        while True:
            finishing = self.done.is_set()
            batches = self.queue.get_all(
                0.0 if finishing else max(0.0, next_flush - time.monotonic())
            )
            for b in batches:
                self._take(b)
            self.events += self.shared.take_events()
            if self.queue.dropped:
                n, self.queue.dropped = self.queue.dropped, 0
                self._drop_event(n, "the writer could not keep up")
            now = time.monotonic()
            if finishing or now >= next_flush:
                period = self.shared.settings.flush_period_s
                next_flush = max(next_flush + period, now + period / 4)
                self._flush(now)
                if now >= self.next_retention and self.file is not None:
                    self._retention()
            if finishing and not batches:
                break
        self._close_file(final=True)
        if self.n_rows:
            log.error("%d scans could not be written before stopping (%s)", self.n_rows,
                      self.status.disk_error or "no file")  # fmt: skip

    def _take(self, batch: Batch) -> None:
        if batch.device is not None:
            self.device = batch.device
        if len(batch.rows):
            self.rows.append(batch.rows)
            self.n_rows += len(batch.rows)
        self.events += batch.events
        cap = self.shared.settings.max_backlog_scans
        if self.n_rows > cap:
            rows = np.concatenate(self.rows)
            drop = len(rows) - cap
            self.rows, self.n_rows = [rows[drop:]], cap
            self._drop_event(drop, "the disk has refused writes for too long")
        if len(self.events) > MAX_PENDING_EVENTS:
            del self.events[: len(self.events) - MAX_PENDING_EVENTS]

    def _event(self, kind: str, level: Level, message: str, **details: object) -> None:
        """An event of the writer's own: counted, logged, and written with the next flush."""
        ev = Event(time.time_ns(), kind, level, message, dict(details))
        self.shared.record(ev, pending=False)
        ev.log(log)
        self.events.append(ev)

    def _drop_event(self, n: int, why: str) -> None:
        self._event("backlog_dropped", Level.ERROR, f"{n} scans dropped from memory: {why}",
                    scans=n)  # fmt: skip

    # ------------------------------------------------------------------ files

    def _rotation_due(self, now: float) -> str:
        f = self.file
        if f is None:
            return ""
        s = self.shared.settings
        if self.shared.rotate:
            return "configuration reloaded"
        if now - self.file_opened >= s.rotate_seconds:
            return f"{s.rotate_seconds:g} s old"
        if f.size >= s.rotate_bytes:
            return f"{f.size} bytes"
        if f.path.parent != s.directory:
            return "directory changed"
        dev, fdev = self.device, self.file_device
        if dev is not None and fdev is not None and dev != fdev:
            return "another module"
        return ""

    def _open_file(self, now: float) -> RecordingWriter:
        s = self.shared.settings
        controller = self.shared.take_rotation()
        durable.make_dirs(s.directory)
        t = time.time_ns()
        path = s.directory / recording_name(t)
        while path.exists():
            t += 1000
            path = s.directory / recording_name(t)
        meta = metadata_records(
            device=self.device.as_metadata() if self.device else {},
            controller=controller.as_metadata(),
            command=self.command,
            extra={
                "flush_period_s": f"{s.flush_period_s:g}",
                "rotate_seconds": f"{s.rotate_seconds:g}",
                "rotate_bytes": str(s.rotate_bytes),
            },
        )
        f = RecordingWriter(path, metadata=meta, params=controller.params,
                            on_views=self.on_views)  # fmt: skip
        self.status.bytes_written += f.size  # its header, schemas and metadata
        self.file, self.file_opened, self.file_device = f, now, self.device
        self.status.file = path
        self.status.files_written += 1
        log.info("recording to %s", path)
        self.next_retention = 0.0
        return f

    def _close_file(self, *, final: bool = False) -> None:
        """Close the current file (summary and index); pending scans wait for the next. A
        file closed by a rotation goes to the compactor (the last one, at a stop, is taken
        by the next start: a stop must not wait for it)."""
        f, self.file = self.file, None
        if f is None:
            return
        try:
            f.close()
            log.info("closed %s: %d scans", f.path, f.scans_written)
            if self.compactor is not None and not final:
                self.compactor.submit(f.path)
        except OSError as exc:
            f.abandon()
            log.error("could not close %s properly: %s (it reads back without its index)",
                      f.path, exc)  # fmt: skip

    def _write(self, f: RecordingWriter, now: float) -> None:
        """Write what is pending; a backlog goes in pieces of BACKLOG_PIECE_NS of scan time,
        each made durable, so a disk with a little room left still takes some of it.

        Within a file stamps never go back: the acquisition's only strictly increase, but
        step back when the host's clock was set back, and a new file starts there."""
        rows = np.concatenate(self.rows) if self.rows else np.zeros(0, dtype=SCAN_DTYPE)
        stamps = rows["stamp_ns"]
        cuts = [0]
        if len(rows):
            pieces = np.flatnonzero(np.diff((stamps - stamps[0]) // BACKLOG_PIECE_NS)) + 1
            back = np.flatnonzero(np.diff(stamps) <= 0) + 1
            cuts += sorted({*pieces.tolist(), *back.tolist()})
        cuts.append(len(rows))
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            last = f.last_stamp_ns
            if a < b and last is not None and stamps[a] <= last:
                log.info("rotating (stamps go back %.3f s: the host's clock was set back)",
                         (last - int(stamps[a])) / 1e9)  # fmt: skip
                self._close_file()
                f = self._open_file(now)
            before = f.size
            f.write(rows[a:b], self.events)
            self.status.bytes_written += f.size - before
            self.events = []
            self.status.scans_written += b - a
            if b > a:
                self.status.written_through_ns = int(stamps[b - 1])
            self.rows, self.n_rows = [rows[b:]], len(rows) - b
        self.rows, self.n_rows = [], 0
        if f.views_error and self.views_reported != f.path:
            self.views_reported = f.path
            self._event("views_failed", Level.ERROR,
                        f"no plate poses for {f.path.name}: the controller config's parameters "
                        f"give no forward kinematics ({f.views_error}); the raw scans are "
                        "recorded", path=str(f.path), error=f.views_error)  # fmt: skip

    def _flush(self, now: float) -> None:
        if not self.rows and (self.file is None or not self.events):
            return  # nothing to write, or only events before the first scan
        if self.disk_error_since is not None and now < self.retry_at:
            self.status.backlog = self.n_rows
            return
        try:
            reason = self._rotation_due(now)
            if reason:
                log.info("rotating (%s)", reason)
                self._close_file()
            f = self.file if self.file is not None else self._open_file(now)
            if self.disk_error_since is not None:
                log.info("retrying: %d scans waiting", self.n_rows)
            self._write(f, now)
        except OSError as exc:
            self._disk_failed(exc, now)
            return
        if self.disk_error_since is not None:
            outage = now - self.disk_error_since
            self.disk_error_since = None
            self.status.disk_error = ""
            self._event("disk_recovered", Level.INFO, f"writing works again after {outage:.1f} s",
                        path=str(self.file.path if self.file else ""),
                        outage_s=round(outage, 3))  # fmt: skip
        self.status.backlog = 0

    def _disk_failed(self, exc: OSError, now: float) -> None:
        f, self.file = self.file, None
        path = f.path if f is not None else self.shared.settings.directory
        if f is not None:
            f.abandon()
            if f.scans_written == 0:  # only a header: leave no husk behind for each retry
                try:
                    f.path.unlink()
                except OSError:
                    pass
        text = f"{errno.errorcode.get(exc.errno or 0, 'error')}: {exc.strerror or exc}"
        self.status.disk_error = text
        self.status.backlog = self.n_rows
        self.retry_at = now + DISK_RETRY_S
        if self.disk_error_since is None:
            self.disk_error_since = self.failing_logged = now
            self._event("disk_error", Level.ERROR,
                        f"cannot write {path}: {text}; keeping scans in memory and retrying "
                        f"every {DISK_RETRY_S:g} s", path=str(path), error=text,
                        errno=exc.errno)  # fmt: skip
        elif now - self.failing_logged >= STILL_FAILING_LOG_S:
            self.failing_logged = now
            log.warning("disk still refuses writes after %.0f s (%s); %d scans waiting in memory",
                        now - self.disk_error_since, text, self.n_rows)  # fmt: skip

    @staticmethod
    def _sync_deleted(path: Path) -> None:
        """The directory synced after ``path`` was deleted: deleted for good before it is
        said (a power cut may bring back a file whose deletion was not synced)."""
        try:
            durable.fsync_dir(path.parent)
        except OSError as exc:
            log.warning(
                "retention: deleted %s, but %s cannot be synced (%s): a power cut "
                "may bring it back",
                path,
                path.parent,
                exc,
            )

    def _retention(self) -> None:
        self.next_retention = time.monotonic() + RETENTION_CHECK_S
        budget = self.shared.settings.disk_budget_bytes
        if not budget or self.file is None:
            return
        try:
            files = find_recordings(self.file.path.parent)
        except Exception:  # noqa: BLE001 - a listing problem shows up as a disk error later
            return
        current = self.file.path
        sizes = []
        for p in files:
            try:
                sizes.append((p, p.stat().st_size))
            except OSError:
                continue
        total = sum(sz for _, sz in sizes)
        for p, sz in sizes:
            if total <= budget:
                break
            if p == current:
                continue
            try:
                with directory_lock(p.parent):  # not while a compaction replaces it
                    p.unlink()
                    self._sync_deleted(p)
            except OSError as exc:
                log.warning("retention: cannot delete %s: %s", p, exc)
                continue
            total -= sz
            self._event("retention", Level.INFO,
                        f"deleted {p.name} ({sz} bytes) to stay under the disk budget of "
                        f"{budget} bytes", path=str(p), bytes=sz)  # fmt: skip
