"""The recording engine: scans from the acquisition thread into rotating MCAP files.

Three threads share the work so that a slow or full disk never delays reading the DAQ:

- the acquisition thread (:class:`~loopcal.daemon.recorder.acquisition.Acquisition`) reads the
  module and puts batches on a :class:`~loopcal.daemon.recorder.filewriter.ScanQueue` without ever
  waiting;
- the writer thread (:class:`~loopcal.daemon.recorder.filewriter.FileWriter`) takes them off and
  writes them to rotating files, riding out disk errors;
- the calling thread (:meth:`Recorder.run`) waits for stop and reload requests (set by
  signal handlers) and keeps systemd informed: READY, STATUS, WATCHDOG.

A fourth, the analysis thread (:mod:`~loopcal.daemon.recorder.observers`), feeds every scan to the
observers the caller adds (live analysis: loop-closure health, guidance); they emit events
through :meth:`Recorder.emit`.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

from ..config.controller import ControllerConfig, load_controller_config, nominal_config
from ..events import Event, Level
from ..recording.views import WrittenViews
from ..times import now_text, time_text
from ..version import loopcal_version
from .acquisition import Acquisition, AcquisitionStats, Batch, ResumePoint
from .compactor import Compactor
from .filewriter import FileWriter, RecorderStatus, ScanQueue, Shared, prepare_directory
from .metrics import MetricsServer
from .observers import AnalysisThread, Observer
from .ownership import ModuleHeld, ModuleLock, module_key
from .resume import last_scan
from .sdnotify import Notifier
from .settings import RecorderSettings

log = logging.getLogger(__name__)

STATUS_PERIOD_S = 5.0
FOLLOW_CONFIG_S = 2.0  # how often the controller config file is looked at for a new version
ACQUISITION_STALE_S = 10.0  # no loop turn for this long: stop feeding the watchdog


class ConfigWatch:
    """Notices that the controller config file was replaced (a calibration wrote a new
    version: another inode) or edited, through a symlink too, from a cheap ``stat``."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self.seen = self.signature()

    def signature(self) -> tuple | None:
        if self.path is None:
            return None
        try:
            st, link = os.stat(self.path), os.lstat(self.path)
        except OSError as exc:
            return ("unreadable", exc.errno)
        return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, link.st_ino, link.st_mtime_ns)

    def changed(self) -> bool:
        """Whether the file is not as last seen (and remember it as it is now)."""
        now = self.signature()
        if now == self.seen:
            return False
        self.seen = now
        return True


class Recorder:
    """Record the DAQ named by the settings until :meth:`request_stop`.

    settings: what to record and where. command: how the recorder was started (metadata).
    service: this is ``loopcal daemon`` (the lock file says so to a second process).
    reload_settings: called on :meth:`request_reload` for the new settings (None: keep the
    settings, re-read the controller config). notifier: systemd notification (None: a
    Notifier from the environment, a no-op outside systemd). The scans also go to every
    observer added with :meth:`add_observer`.

    Before anything else it takes the module's lock
    (:class:`~loopcal.daemon.recorder.ownership.ModuleLock`), and raises
    :class:`~loopcal.daemon.recorder.ownership.ModuleHeld` naming the holder if another
    process on this host records the module; it keeps the lock until :meth:`run` returns.
    """

    def __init__(
        self,
        settings: RecorderSettings,
        *,
        command: str,
        service: bool = False,
        reload_settings: Callable[[], RecorderSettings] | None = None,
        notifier: Notifier | None = None,
    ) -> None:
        self.command = command
        self.service = service
        self.module_lock = ModuleLock(settings.daq_url, command=command, service=service)
        self._reload_settings = reload_settings
        self.notifier = notifier if notifier is not None else Notifier()
        prepare_directory(settings.directory)
        self.shared = Shared(settings, self._load_controller(settings))
        self.status = RecorderStatus()
        self.exit_reason = ""
        self._stop = threading.Event()
        self._reload = threading.Event()
        self._signalled_stop = ""  # signal_stop's reason, for the loop to act on
        self._signalled_reload = False
        self._acq_stop = threading.Event()
        self._writer_done = threading.Event()
        self._queue = ScanQueue(settings.max_backlog_scans)
        self._acq: Acquisition | None = None
        self._acq_thread: threading.Thread | None = None
        self._writer_thread: threading.Thread | None = None
        self._fatal: BaseException | None = None
        self.analysis = AnalysisThread([])
        self._watch = ConfigWatch(settings.controller_config)
        self.followed = ""  # what the status line says after following a replaced config
        #: when the newest scan arrived, ns since the Unix epoch (None before the first)
        self.last_scan_ns: int | None = None
        #: called with every event as it is emitted, from the emitting thread (the live
        #: view); each must return at once
        self.event_listeners: list[Callable[[Event], None]] = []
        #: called with the views of the scans each write put in the recording (the live
        #: view, which so does not compute them again), from the writer thread; each must
        #: return at once
        self.view_listeners: list[Callable[[WrittenViews], None]] = []
        #: called in :meth:`run`'s thread as it stops, before the acquisition stops and the
        #: last scans are written (a technician's session ends there, so that its end and
        #: its scans reach the recording)
        self.stop_listeners: list[Callable[[], None]] = []
        self.compactor = Compactor(lambda: self.settings.keep_views_days) \
            if settings.compact else None  # fmt: skip
        self.metrics: MetricsServer | None = None
        if settings.metrics_listen:
            self.metrics = MetricsServer(self, settings.metrics_listen)

    @property
    def settings(self) -> RecorderSettings:
        """The settings in force (a reload may replace them)."""
        return self.shared.settings

    @property
    def controller(self) -> ControllerConfig:
        """The controller config in force (a reload may replace it)."""
        return self.shared.controller

    # ------------------------------------------------------------------ control

    def add_observer(self, observer: Observer) -> None:
        """Feed the scans to ``observer`` too (:mod:`~loopcal.daemon.recorder.observers`); before
        :meth:`run`. On a reload it gets the new controller config."""
        self.analysis.observers.append(observer)

    def request_stop(self, reason: str = "stop requested") -> None:
        """Stop: close the file properly and return from :meth:`run` (from any thread; a
        signal handler calls :meth:`signal_stop`)."""
        if not self.exit_reason:
            self.exit_reason = reason
        self._stop.set()

    def request_reload(self) -> None:
        """Reload the settings and the controller config, and start a new file."""
        self._reload.set()

    def signal_stop(self, reason: str) -> None:
        """:meth:`request_stop` from a signal handler: only noted, no lock taken, and acted
        on by :meth:`run`'s loop within its 0.2 s wait. A handler runs in the main thread,
        which may be inside ``Event.wait`` holding the very lock ``Event.set`` takes (ci79:
        SIGTERM there hung the daemon until it was killed)."""
        self._signalled_stop = self._signalled_stop or reason

    def signal_reload(self) -> None:
        """:meth:`request_reload` from a signal handler (:meth:`signal_stop` says why)."""
        self._signalled_reload = True

    @staticmethod
    def _load_controller(settings: RecorderSettings) -> ControllerConfig:
        if settings.controller_config is None:
            return nominal_config()
        return load_controller_config(settings.controller_config)

    def emit(self, kind: str, level: Level, message: str, **details: object) -> None:
        """Record an event (the recorder's own, or an observer's): logged now, written with
        the next flush. Safe from any thread."""
        ev = Event(time.time_ns(), kind, level, message, dict(details))
        ev.log(log)
        self.shared.record(ev)
        self._queue.wake()
        for listener in self.event_listeners:
            try:
                listener(ev)
            except Exception:  # noqa: BLE001 - a listener (the live view) never stops recording
                log.exception("an event listener failed")

    def _views(self, views: WrittenViews) -> None:
        for listener in self.view_listeners:
            try:
                listener(views)
            except Exception:  # noqa: BLE001 - a listener (the live view) never stops recording
                log.exception("a listener of the views failed")

    def event_counts(self) -> Counter[tuple[str, str]]:
        """How many events of each (kind, level) the recorder has recorded so far (its own,
        the acquisition's, the writer's, the observers')."""
        return self.shared.event_counts()

    # ------------------------------------------------------------------ main thread

    def run(self) -> int:
        """Record until stopped; returns the exit status (0, or 1 after an internal error)."""
        s = self.settings
        resume = self._resume_point(s.directory)
        self.emit(
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
        self._emit_lock()
        self.analysis.start()
        if self.compactor is not None:
            self.compactor.start(s.directory)
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
        next_look = time.monotonic() + FOLLOW_CONFIG_S
        while not self._stop.is_set():
            now = time.monotonic()
            if self._signalled_stop:
                self.request_stop(self._signalled_stop)
                break
            if self._signalled_reload:
                self._signalled_reload = False
                self._reload.set()
            if t_end is not None and now >= t_end:
                self.request_stop(f"--duration {s.duration_s:g} s reached")
                break
            if self._fatal is not None or not self._writer_thread.is_alive():
                self.request_stop("internal error")
                break
            if self._reload.is_set():
                self._reload.clear()
                self._do_reload()
            elif now >= next_look:
                next_look = now + FOLLOW_CONFIG_S
                if self._watch.changed():
                    self._follow_config()
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
        for listener in self.stop_listeners:
            try:
                listener()
            except Exception:  # noqa: BLE001 - stopping goes on, whatever a listener does
                log.exception("a stop listener failed")
        self._stop_acquisition()
        self.analysis.stop()
        self.emit("recorder_stop", Level.INFO, f"recorder stopping: {self.exit_reason}",
                    reason=self.exit_reason)  # fmt: skip
        self._writer_done.set()
        self._queue.wake()
        self._writer_thread.join(30.0)
        if self.compactor is not None:
            self.compactor.stop(timeout=0.0)  # a compaction cut short is redone next time
        if self.metrics is not None:
            self.metrics.close()
        self.module_lock.release()
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
            if a.foreign_since_ns is not None:
                parts.append(f"ANOTHER MODBUS MASTER is taking scans off the DAQ's FIFO since "
                             f"{time_text(a.foreign_since_ns)} "
                             f"({a.foreign_taken} taken in all)")  # fmt: skip
            why = acq.diagnosis
            parts.append(
                "DAQ connected"
                if a.connected
                else f"DAQ unreachable [{why.cause}]: {why.message}"
                if why is not None
                else f"DAQ unreachable: {a.last_error or 'connecting'}"
            )
        parts += self.analysis.status()
        if self.followed:
            parts.append(self.followed)
        return "; ".join(parts)

    def _emit_lock(self) -> None:
        lock = self.module_lock
        self.emit("module_held", Level.INFO,
                  f"this process is the module's one owner on this host ({lock.key}: "
                  f"{lock.path})", key=lock.key, lock=str(lock.path))  # fmt: skip

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
            self.emit("damaged_recording", Level.WARNING, text, directory=str(directory))
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
            report_every=s.unreachable_report_s,
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
        if len(batch.rows):
            self.last_scan_ns = int(batch.rows["host_ns"][-1])
        for ev in batch.events:  # written with the batch's scans
            self.shared.record(ev, pending=False)

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
        lock = None
        try:
            new = self._reload_settings() if self._reload_settings is not None else old
            controller = self._load_controller(new)
            if new.directory != old.directory:
                prepare_directory(new.directory)
            if module_key(new.daq_url) != self.module_lock.key:  # another module
                lock = ModuleLock(new.daq_url, command=self.command, service=self.service)
        except (ValueError, OSError, ModuleHeld) as exc:
            holder = getattr(exc, "holder", None)
            self.emit("module_held" if holder is not None else "config_reload", Level.ERROR,
                      f"reload failed, keeping the running configuration: {exc}",
                      ok=False, error=str(exc),
                      **({"holder": holder.__dict__} if holder is not None else {}))  # fmt: skip
            self.notifier.ready(self.status_line())
            return
        self._put_in_force(controller, new)
        self._watch = ConfigWatch(new.controller_config)
        if self._acq is not None:
            self._acq.report_every = new.unreachable_report_s
        restart_daq = (new.daq_url, new.timeout_s, new.read_period_s) != (
            old.daq_url, old.timeout_s, old.read_period_s)  # fmt: skip
        if restart_daq:
            self._stop_acquisition()
            if lock is not None:  # the new module's lock, taken above; the old one let go
                self.module_lock.release()
                self.module_lock = lock
                self._emit_lock()
            acq = self._acq
            self._start_acquisition(acq.resume_point if acq is not None else None)
        self.emit("config_reload", Level.INFO,
                    f"configuration reloaded (controller config {controller.path or 'reference'}"
                    f"{', DAQ reopened' if restart_daq else ''}); starting a new file",
                    ok=True, controller_sha256=controller.sha256)  # fmt: skip
        self.notifier.ready(self.status_line())

    def _put_in_force(self, controller: ControllerConfig,
                      settings: RecorderSettings | None = None) -> None:  # fmt: skip
        """Record with ``controller`` (and ``settings``, if given) from a new file on, which
        is asked for; the observers get the controller at once."""
        with self.shared.lock:
            if settings is not None:
                self.shared.settings = settings
                self._queue.cap = settings.max_backlog_scans
            self.shared.controller = controller
            self.shared.rotate = True
        self.analysis.reload(controller)

    def _follow_config(self) -> None:
        """The controller config file changed on disk (``loopcal calibrate --write``, the
        worker unit, an edit): load it and go on with it, as a reload would, without being
        told. A config that does not load is refused and the running one kept."""
        path = self.settings.controller_config
        try:
            controller = self._load_controller(self.settings)
        except (ValueError, OSError) as exc:
            self.emit("config_reload", Level.ERROR,
                      f"the controller config {path} changed but does not load, keeping the "
                      f"running one: {exc}", ok=False, trigger="file changed",
                      error=str(exc))  # fmt: skip
            return
        if controller.sha256 == self.controller.sha256:
            return  # touched, not changed
        self._put_in_force(controller)
        prov = controller.provenance or {}
        how = (f" (calibrated {prov.get('written_utc', '?')} by {prov.get('method', '?')})"
               if prov else "")  # fmt: skip
        self.followed = (f"controller config replaced {now_text()}: following sha256 "
                         f"{controller.sha256[:12]}{how}")  # fmt: skip
        self.emit("config_reload", Level.INFO,
                  f"the controller config {path} was replaced{how}: following it from now "
                  "on, in a new file", ok=True, trigger="file changed",
                  controller_sha256=controller.sha256,
                  provenance=json.loads(json.dumps(prov, default=str)))  # fmt: skip
        self.notifier.status(self.status_line())

    # ------------------------------------------------------------------ writer thread

    def _writer_main(self) -> None:
        try:
            FileWriter(self._queue, self.shared, self.status, command=self.command,
                       done=self._writer_done, compactor=self.compactor,
                       on_views=self._views if self.view_listeners else None).run()  # fmt: skip
        except BaseException as exc:  # noqa: BLE001 - reported, and the recorder stops
            log.exception("writer thread failed")
            self._fatal = exc
            self._stop.set()


