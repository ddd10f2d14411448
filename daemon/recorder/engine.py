"""The recording engine: scans from the acquisition thread into rotating MCAP files.

Three threads share the work so that a slow or full disk never delays reading the DAQ:

- the acquisition thread (:class:`~daemon.recorder.acquisition.Acquisition`) reads the
  module and puts batches on a :class:`ScanQueue` without ever waiting;
- the writer thread takes them off, and every flush period writes them to the current file
  (:class:`daemon.recording.RecordingWriter`) and fsyncs; it rotates files by age, size,
  reload and device change, deletes the oldest recordings to stay under the disk budget, and
  rides out disk errors: the scans stay in memory (up to ``max_backlog_scans``), it retries
  every few seconds, and writes them all once the disk takes them again;
- the calling thread (:meth:`Recorder.run`) waits for stop and reload requests (set by
  signal handlers) and keeps systemd informed: READY, STATUS, WATCHDOG.
"""

from __future__ import annotations

import collections
import errno
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config.controller import ControllerConfig, load_controller_config, nominal_config
from ..events import Event, Level
from ..live.health import HealthMonitor
from ..recording import RecordingWriter, find_recordings, metadata_records, recording_name
from ..scans import SCAN_DTYPE
from ..version import loopcal_version
from .acquisition import Acquisition, AcquisitionStats, Batch, DeviceInfo, ResumePoint
from .observers import AnalysisThread, Observer
from .resume import last_scan
from .sdnotify import Notifier
from .settings import RecorderSettings, SettingsError

log = logging.getLogger("daemon.recorder.engine")

DISK_RETRY_S = 5.0  # how often to try again while the disk refuses to write
RETENTION_CHECK_S = 30.0
STATUS_PERIOD_S = 5.0
ACQUISITION_STALE_S = 10.0  # no loop turn for this long: stop feeding the watchdog
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
        return SettingsError(f"[recording].directory: {directory}: {what}{why}")

    try:
        directory.mkdir(parents=True, exist_ok=True)
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
    disk_error: str = ""
    backlog: int = 0


class Recorder:
    """Record the DAQ named by the settings until :meth:`request_stop`.

    settings: what to record and where. command: how the recorder was started (metadata).
    reload_settings: called on :meth:`request_reload` for the new settings (None: keep the
    settings, re-read the controller config). notifier: systemd notification (None: a
    Notifier from the environment, a no-op outside systemd). The scans also go to the
    loop-closure health monitor (:mod:`daemon.live.health`, unless ``settings.health`` is off)
    and to any observer added with :meth:`add_observer`.
    """

    def __init__(
        self,
        settings: RecorderSettings,
        *,
        command: str,
        reload_settings: Callable[[], RecorderSettings] | None = None,
        notifier: Notifier | None = None,
    ) -> None:
        self.settings = settings
        self.command = command
        self._reload_settings = reload_settings
        self.notifier = notifier if notifier is not None else Notifier()
        prepare_directory(settings.directory)
        self.controller = self._load_controller(settings)
        self.status = RecorderStatus()
        self.exit_reason = ""
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._acq_stop = threading.Event()
        self._writer_done = threading.Event()
        self._lock = threading.Lock()
        self._queue = ScanQueue(settings.max_backlog_scans)
        self._acq: Acquisition | None = None
        self._acq_thread: threading.Thread | None = None
        self._writer_thread: threading.Thread | None = None
        self._fatal: BaseException | None = None
        self._rotate = False
        self._writer_heartbeat = time.monotonic()
        self._local_events: list[Event] = []
        self.health: HealthMonitor | None = None
        if settings.health:
            self.health = HealthMonitor(
                self.controller, self._event, false_alarm=settings.health_false_alarm
            )
        self.analysis = AnalysisThread([self.health] if self.health is not None else [])

    # ------------------------------------------------------------------ control

    def add_observer(self, observer: Observer) -> None:
        """Feed the scans to ``observer`` too (:mod:`~daemon.recorder.observers`); before
        :meth:`run`."""
        self.analysis.observers.append(observer)

    def request_stop(self, reason: str = "stop requested") -> None:
        """Stop: close the file properly and return from :meth:`run` (signal-safe)."""
        if not self.exit_reason:
            self.exit_reason = reason
        self._stop.set()

    def request_reload(self) -> None:
        """Reload the settings and the controller config, and start a new file."""
        self._reload.set()

    @staticmethod
    def _load_controller(settings: RecorderSettings) -> ControllerConfig:
        if settings.controller_config is None:
            return nominal_config()
        return load_controller_config(settings.controller_config)

    def _event(self, kind: str, level: Level, message: str, **details: object) -> None:
        """An event raised by the recorder itself (written with the next flush)."""
        ev = Event(time.time_ns(), kind, level, message, dict(details))
        ev.log(log)
        with self._lock:
            self._local_events.append(ev)
        self._queue.wake()

    # ------------------------------------------------------------------ main thread

    def run(self) -> int:
        """Record until stopped; returns the exit status (0, or 1 after an internal error)."""
        s = self.settings
        resume = self._resume_point(s.directory)
        self._event(
            "recorder_start",
            Level.INFO,
            f"loopcal {loopcal_version()} recording {s.daq_url} into {s.directory}",
            version=loopcal_version(),
            pid=os.getpid(),
            url=s.daq_url,
            directory=str(s.directory),
            controller_config=str(self.controller.path or "reference geometry"),
            resume=None if resume is None else resume.__dict__,
        )
        self.analysis.start()
        self._start_acquisition(resume)
        self._writer_thread = threading.Thread(
            target=self._writer_main, name="loopcal-writer", daemon=True
        )
        self._writer_thread.start()
        self.notifier.ready(self.status_line())
        t_end = None if s.duration_s is None else time.monotonic() + s.duration_s
        wd = self.notifier.watchdog_interval
        next_wd = time.monotonic()
        next_status = time.monotonic() + 1.0
        while not self._stop.is_set():
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                self.request_stop(f"--duration {s.duration_s:g} s reached")
                break
            if self._fatal is not None or not self._writer_thread.is_alive():
                self.request_stop("internal error")
                break
            if self._reload.is_set():
                self._reload.clear()
                self._do_reload()
            if wd is not None and now >= next_wd:
                if self._healthy(now):
                    self.notifier.watchdog()
                next_wd = now + wd
            if now >= next_status:
                self.notifier.status(self.status_line())
                next_status = now + STATUS_PERIOD_S
            timeout = 0.2
            if t_end is not None:
                timeout = min(timeout, max(0.0, t_end - now))
            self._stop.wait(timeout)
        self.notifier.stopping(f"stopping: {self.exit_reason}")
        self._stop_acquisition()
        self.analysis.stop()
        self._event("recorder_stop", Level.INFO, f"recorder stopping: {self.exit_reason}",
                    reason=self.exit_reason)  # fmt: skip
        self._writer_done.set()
        self._queue.wake()
        self._writer_thread.join(30.0)
        if self._fatal is not None:
            log.critical("internal error: %r", self._fatal)
            return 1
        return 0

    @property
    def acquisition_stats(self) -> AcquisitionStats | None:
        return self._acq.stats if self._acq is not None else None

    def _healthy(self, now: float) -> bool:
        acq = self._acq
        return (
            acq is not None
            and now - acq.heartbeat < ACQUISITION_STALE_S
            and self._acq_thread is not None
            and self._acq_thread.is_alive()
        )

    def status_line(self) -> str:
        """One line for ``systemctl status``: file, scans, gaps, DAQ state."""
        st = self.status
        acq = self._acq
        parts = []
        if st.disk_error:
            parts.append(f"DISK ERROR ({st.disk_error}), {st.backlog} scans waiting in memory")
        parts.append(f"recording {st.file.name}" if st.file else "no file open")
        parts.append(f"{st.scans_written:,} scans written")
        if acq is not None:
            a = acq.stats
            parts.append(f"{a.gaps} gaps ({a.missed} missed)")
            if a.restarts:
                parts.append(f"{a.restarts} module restarts")
            parts.append(
                "DAQ connected"
                if a.connected
                else f"DAQ unreachable: {a.last_error or 'connecting'}"
            )
        parts += self.analysis.status()
        return "; ".join(parts)

    def _resume_point(self, directory: Path) -> ResumePoint | None:
        """Where the last recording of the directory ended. Damaged or unreadable files
        never stop the recorder: each is reported as a ``damaged_recording`` event, and it
        carries on from the last intact scan (or from nothing)."""
        problems: list[str] = []
        found = None
        try:
            found = last_scan(directory, problems) if directory.is_dir() else None
            resume = None if found is None else ResumePoint.from_row(found[0], found[1].get(
                "device", {}))  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - an old file must never stop the recording
            log.exception("cannot look for the last recorded scan in %s", directory)
            problems.append(f"{directory}: the last recorded scan could not be read ({exc!r}); "
                            "starting a new power-on epoch")  # fmt: skip
            resume = None
        for text in problems:
            self._event("damaged_recording", Level.WARNING, text, directory=str(directory))
        return resume

    def _start_acquisition(self, resume: ResumePoint | None) -> None:
        s = self.settings
        self._acq_stop = threading.Event()
        self._acq = Acquisition(
            s.daq_url,
            self._put,
            timeout=s.timeout_s,
            read_period=s.read_period_s,
            resume=resume,
        )
        self._acq_thread = threading.Thread(
            target=self._acq_main, args=(self._acq, self._acq_stop), name="loopcal-acq",
            daemon=True,
        )  # fmt: skip
        self._acq_thread.start()

    def _put(self, batch: Batch) -> None:
        """The acquisition's output: to the writer, and to the observers (never blocks)."""
        self._queue.put(batch)
        self.analysis.put(batch.rows)

    def _acq_main(self, acq: Acquisition, stop: threading.Event) -> None:
        try:
            acq.run(stop)
        except BaseException as exc:  # noqa: BLE001 - reported, and the recorder stops
            log.exception("acquisition thread failed")
            self._fatal = exc
            self._stop.set()

    def _stop_acquisition(self) -> None:
        self._acq_stop.set()
        if self._acq_thread is not None:
            self._acq_thread.join(5.0)

    def _do_reload(self) -> None:
        self.notifier.reloading()
        old = self.settings
        try:
            new = self._reload_settings() if self._reload_settings is not None else old
            controller = self._load_controller(new)
            if new.directory != old.directory:
                prepare_directory(new.directory)
        except (ValueError, OSError) as exc:
            self._event("config_reload", Level.ERROR,
                        f"reload failed, keeping the running configuration: {exc}",
                        ok=False, error=str(exc))  # fmt: skip
            self.notifier.ready(self.status_line())
            return
        with self._lock:
            self.settings = new
            self.controller = controller
            self._queue.cap = new.max_backlog_scans
            self._rotate = True
        if self.health is not None:
            self.analysis.call(self.health.reset, controller)
        restart_daq = (new.daq_url, new.timeout_s, new.read_period_s) != (
            old.daq_url, old.timeout_s, old.read_period_s)  # fmt: skip
        if restart_daq:
            self._stop_acquisition()
            acq = self._acq
            self._start_acquisition(acq.resume_point if acq is not None else None)
        self._event("config_reload", Level.INFO,
                    f"configuration reloaded (controller config {controller.path or 'reference'}"
                    f"{', DAQ reopened' if restart_daq else ''}); starting a new file",
                    ok=True, controller_sha256=controller.sha256)  # fmt: skip
        self.notifier.ready(self.status_line())

    # ------------------------------------------------------------------ writer thread

    def _writer_main(self) -> None:
        try:
            _Writer(self).run()
        except BaseException as exc:  # noqa: BLE001 - reported, and the recorder stops
            log.exception("writer thread failed")
            self._fatal = exc
            self._stop.set()


class _Writer:
    """The writer thread's state: pending scans, the current file, disk errors."""

    def __init__(self, rec: Recorder) -> None:
        self.rec = rec
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
        rec = self.rec
        period = rec.settings.flush_period_s
        next_flush = time.monotonic() + period
        while True:
            rec._writer_heartbeat = time.monotonic()
            finishing = rec._writer_done.is_set()
            batches = rec._queue.get_all(
                0.0 if finishing else max(0.0, next_flush - time.monotonic())
            )
            for b in batches:
                self._take(b)
            with rec._lock:
                self.events += rec._local_events
                rec._local_events = []
            if rec._queue.dropped:
                n, rec._queue.dropped = rec._queue.dropped, 0
                self._drop_event(n, "the writer could not keep up")
            now = time.monotonic()
            if finishing or now >= next_flush:
                period = rec.settings.flush_period_s
                next_flush = max(next_flush + period, now + period / 4)
                self._flush(now)
                if now >= self.next_retention and self.file is not None:
                    self._retention()
            if finishing and not batches:
                break
        self._close_file()
        if self.n_rows:
            log.error("%d scans could not be written before stopping (%s)", self.n_rows,
                      self.rec.status.disk_error or "no file")  # fmt: skip

    def _take(self, batch: Batch) -> None:
        if batch.device is not None:
            self.device = batch.device
        if len(batch.rows):
            self.rows.append(batch.rows)
            self.n_rows += len(batch.rows)
        self.events += batch.events
        cap = self.rec.settings.max_backlog_scans
        if self.n_rows > cap:
            rows = np.concatenate(self.rows)
            drop = len(rows) - cap
            self.rows, self.n_rows = [rows[drop:]], cap
            self._drop_event(drop, "the disk has refused writes for too long")
        if len(self.events) > MAX_PENDING_EVENTS:
            del self.events[: len(self.events) - MAX_PENDING_EVENTS]

    def _drop_event(self, n: int, why: str) -> None:
        self.events.append(
            Event(
                time.time_ns(),
                "backlog_dropped",
                Level.ERROR,
                f"{n} scans dropped from memory: {why}",
                {"scans": n},
            )  # fmt: skip
        )
        self.events[-1].log(log)

    # ------------------------------------------------------------------ files

    def _rotation_due(self, now: float) -> str:
        rec, f = self.rec, self.file
        if f is None:
            return ""
        s = rec.settings
        if rec._rotate:
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
        rec = self.rec
        s = rec.settings
        with rec._lock:
            rec._rotate = False
            controller = rec.controller
        s.directory.mkdir(parents=True, exist_ok=True)
        t = time.time_ns()
        path = s.directory / recording_name(t)
        while path.exists():
            t += 1000
            path = s.directory / recording_name(t)
        meta = metadata_records(
            device=self.device.as_metadata() if self.device else {},
            controller=controller.as_metadata(),
            command=rec.command,
            extra={
                "flush_period_s": f"{s.flush_period_s:g}",
                "rotate_seconds": f"{s.rotate_seconds:g}",
                "rotate_bytes": str(s.rotate_bytes),
            },
        )
        f = RecordingWriter(path, metadata=meta, params=controller.params)
        self.file, self.file_opened, self.file_device = f, now, self.device
        rec.status.file = path
        rec.status.files_written += 1
        log.info("recording to %s", path)
        self.next_retention = 0.0
        return f

    def _close_file(self) -> None:
        """Close the current file (summary and index); pending scans wait for the next."""
        f, self.file = self.file, None
        if f is None:
            return
        try:
            f.close()
            log.info("closed %s: %d scans", f.path, f.scans_written)
        except OSError as exc:
            f.abandon()
            log.error("could not close %s properly: %s (it reads back without its index)",
                      f.path, exc)  # fmt: skip

    def _write(self, f: RecordingWriter) -> None:
        """Write what is pending; a backlog goes in pieces of BACKLOG_PIECE_NS of scan time,
        each made durable, so a disk with a little room left still takes some of it."""
        rows = np.concatenate(self.rows) if self.rows else np.zeros(0, dtype=SCAN_DTYPE)
        stamps = rows["stamp_ns"]
        cuts = [0]
        if len(rows):
            cuts += list(np.flatnonzero(np.diff((stamps - stamps[0]) // BACKLOG_PIECE_NS)) + 1)
        cuts.append(len(rows))
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            f.write(rows[a:b], self.events)
            self.events = []
            self.rec.status.scans_written += b - a
            self.rows, self.n_rows = [rows[b:]], len(rows) - b
        self.rows, self.n_rows = [], 0
        if f.views_error and self.views_reported != f.path:
            self.views_reported = f.path
            ev = Event(time.time_ns(), "views_failed", Level.ERROR,
                       f"no plate poses for {f.path.name}: the controller config's parameters "
                       f"give no forward kinematics ({f.views_error}); the raw scans are "
                       "recorded", {"path": str(f.path), "error": f.views_error})  # fmt: skip
            ev.log(log)
            self.events.append(ev)

    def _flush(self, now: float) -> None:
        rec = self.rec
        if not self.rows and (self.file is None or not self.events):
            return  # nothing to write, or only events before the first scan
        if self.disk_error_since is not None and now < self.retry_at:
            rec.status.backlog = self.n_rows
            return
        try:
            reason = self._rotation_due(now)
            if reason:
                log.info("rotating (%s)", reason)
                self._close_file()
            f = self.file if self.file is not None else self._open_file(now)
            if self.disk_error_since is not None:
                log.info("retrying: %d scans waiting", self.n_rows)
            self._write(f)
        except OSError as exc:
            self._disk_failed(exc, now)
            return
        if self.disk_error_since is not None:
            outage = now - self.disk_error_since
            self.disk_error_since = None
            rec.status.disk_error = ""
            ev = Event(time.time_ns(), "disk_recovered", Level.INFO,
                       f"writing works again after {outage:.1f} s", {
                           "path": str(self.file.path if self.file else ""),
                           "outage_s": round(outage, 3)})  # fmt: skip
            ev.log(log)
            self.events.append(ev)
        rec.status.backlog = 0

    def _disk_failed(self, exc: OSError, now: float) -> None:
        rec = self.rec
        f, self.file = self.file, None
        path = f.path if f is not None else rec.settings.directory
        if f is not None:
            f.abandon()
            if f.scans_written == 0:  # only a header: leave no husk behind for each retry
                try:
                    f.path.unlink()
                except OSError:
                    pass
        text = f"{errno.errorcode.get(exc.errno or 0, 'error')}: {exc.strerror or exc}"
        rec.status.disk_error = text
        rec.status.backlog = self.n_rows
        self.retry_at = now + DISK_RETRY_S
        if self.disk_error_since is None:
            self.disk_error_since = self.failing_logged = now
            ev = Event(time.time_ns(), "disk_error", Level.ERROR,
                       f"cannot write {path}: {text}; keeping scans in memory and retrying "
                       f"every {DISK_RETRY_S:g} s", {"path": str(path), "error": text,
                                                     "errno": exc.errno})  # fmt: skip
            ev.log(log)
            self.events.append(ev)
        elif now - self.failing_logged >= STILL_FAILING_LOG_S:
            self.failing_logged = now
            log.warning("disk still refuses writes after %.0f s (%s); %d scans waiting in memory",
                        now - self.disk_error_since, text, self.n_rows)  # fmt: skip

    def _retention(self) -> None:
        rec = self.rec
        self.next_retention = time.monotonic() + RETENTION_CHECK_S
        budget = rec.settings.disk_budget_bytes
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
                p.unlink()
            except OSError as exc:
                log.warning("retention: cannot delete %s: %s", p, exc)
                continue
            total -= sz
            ev = Event(time.time_ns(), "retention", Level.INFO,
                       f"deleted {p.name} ({sz} bytes) to stay under the disk budget of "
                       f"{budget} bytes", {"path": str(p), "bytes": sz})  # fmt: skip
            ev.log(log)
            self.events.append(ev)
