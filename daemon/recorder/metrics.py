"""Prometheus metrics of a running recorder, on ``http://HOST:PORT/metrics``.

With ``[metrics] listen = "127.0.0.1:9464"`` in the daemon's config (or ``loopcal record
--metrics HOST:PORT``) the recorder serves its state the way the operator's monitoring
expects every service to: a Prometheus endpoint (prometheus-client's own HTTP server, in a
thread of its own). Nothing is counted per scan for it: each scrape reads the recorder's
counters and status as they are (docs/daemon.md lists every metric, and example alert
rules). Observers add their own (the loop-closure health: per sensor).
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import threading
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Protocol
from wsgiref.simple_server import WSGIRequestHandler, make_server

from prometheus_client import CollectorRegistry, make_wsgi_app
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import ThreadingWSGIServer
from prometheus_client.registry import Collector

from ..config.controller import ControllerConfig
from ..recording import find_recordings
from ..times import parse_time
from ..version import loopcal_version
from .acquisition import AcquisitionStats
from .filewriter import RecorderStatus
from .observers import AnalysisThread
from .settings import RecorderSettings, SettingsError, parse_listen


class MetricsSource(Protocol):
    """What the metrics read of a recorder (:class:`loopcal.daemon.recorder.engine.Recorder`)."""

    status: RecorderStatus
    analysis: AnalysisThread
    last_scan_ns: int | None

    @property
    def settings(self) -> RecorderSettings: ...

    @property
    def controller(self) -> ControllerConfig: ...

    @property
    def acquisition_stats(self) -> AcquisitionStats | None: ...

    def event_counts(self) -> Counter[tuple[str, str]]: ...

#: the recording directory is listed at most this often (a scrape every few seconds must
#: not list a directory of thousands of files each time)
DIRECTORY_EVERY_S = 30.0


class RecorderCollector(Collector):
    """The recorder's metrics, read at each scrape."""

    def __init__(self, recorder: MetricsSource) -> None:
        self.rec = recorder
        self._dir_bytes = (0.0, 0)  # (monotonic time measured, bytes)
        #: when the recorder started (its metrics with it), s since the Unix epoch
        self.started_s = time.time()

    def collect(self) -> Iterator[Metric]:
        rec = self.rec
        st = rec.status
        s = rec.settings
        yield _gauge("loopcal_build_info", "loopcal's version", 1, version=loopcal_version())
        yield _gauge("loopcal_recorder_start_time_seconds",
                     "when the recorder started, s since the Unix epoch",
                     self.started_s)  # fmt: skip
        yield _counter("loopcal_scans_recorded", "scans written to the recordings",
                       st.scans_written)  # fmt: skip
        yield _counter("loopcal_bytes_written", "bytes written to recording files",
                       st.bytes_written)  # fmt: skip
        yield _counter("loopcal_recording_files", "recording files started",
                       st.files_written)  # fmt: skip
        acq = rec.acquisition_stats
        yield _counter("loopcal_scans_missed", "scans the module made that were never received",
                       acq.missed if acq else 0)  # fmt: skip
        yield _counter("loopcal_gaps", "gaps in the scan counter (one or more scans missed)",
                       acq.gaps if acq else 0)  # fmt: skip
        yield _counter("loopcal_module_restarts", "restarts (power cycles) of the module",
                       acq.restarts if acq else 0)  # fmt: skip
        yield _counter("loopcal_daq_read_errors", "DAQ reads that failed (no answer in time, "
                       "a malformed answer, no connection)",
                       acq.read_errors if acq else 0)  # fmt: skip
        yield _counter("loopcal_daq_late_answers", "FIFO reads answered after the timeout, "
                       "their scans kept", acq.late_answers if acq else 0)  # fmt: skip
        yield _counter("loopcal_daq_foreign_reader_scans", "scans another Modbus master took off "
                       "the module's FIFO (each also counted as missed)",
                       acq.foreign_taken if acq else 0)  # fmt: skip
        yield _gauge("loopcal_daq_foreign_reader_active", "1 while another Modbus master takes "
                     "scans off the module's FIFO (a foreign_reader episode is on)",
                     1 if acq is not None and acq.foreign_active else 0)  # fmt: skip
        events = rec.event_counts()
        reconnects = sum(n for (kind, _), n in events.items() if kind == "connect")
        yield _counter("loopcal_daq_connects", "times the DAQ answered after being unreachable "
                       "(the first connect included)", reconnects)  # fmt: skip
        fam = CounterMetricFamily("loopcal_events", "events recorded, by kind and level",
                                  labels=["kind", "level"])  # fmt: skip
        for (kind, level), n in sorted(events.items()):
            fam.add_metric([kind, level], n)
        yield fam
        yield _gauge("loopcal_daq_connected", "1 while the DAQ answers",
                     1 if acq is not None and acq.connected else 0)  # fmt: skip
        # Before the first scan the age is absent, not NaN (which no alert rule's comparison
        # is ever true of): a rule tells "no scan yet" by the start time (docs/daemon.md).
        last = rec.last_scan_ns
        if last is not None:
            yield _gauge("loopcal_last_scan_age_seconds", "seconds since the newest scan arrived "
                         "(absent before the first)", (time.time_ns() - last) / 1e9)  # fmt: skip
        yield _gauge("loopcal_disk_error", "1 while the disk refuses writes",
                     1 if st.disk_error else 0)  # fmt: skip
        yield _gauge("loopcal_backlog_scans", "scans waiting in memory for the disk", st.backlog)
        used = self._directory_bytes(s.directory)
        yield _gauge("loopcal_recording_directory_bytes",
                     "bytes of recordings in the recording directory", used)  # fmt: skip
        yield _gauge("loopcal_recording_budget_bytes",
                     "the disk budget of the recording directory (0: none)",
                     s.disk_budget_bytes)  # fmt: skip
        if s.disk_budget_bytes:
            yield _gauge("loopcal_recording_budget_used_ratio",
                         "the recording directory's use of its disk budget",
                         used / s.disk_budget_bytes)  # fmt: skip
        cfg = rec.controller
        prov = cfg.provenance or {}
        yield _gauge("loopcal_controller_config_info", "the controller config in force", 1,
                     path=str(cfg.path or ""), sha256=cfg.sha256,
                     method=str(prov.get("method", "")))  # fmt: skip
        # Never calibrated is a state of its own (0), not a NaN age: an alert rule compares
        # the age, and NaN > x is never true. The age is there only when it is known.
        age = _age_s(prov.get("written_utc"))
        yield _gauge("loopcal_controller_config_calibrated",
                     "1 if loopcal calibrated the controller config in force (its provenance "
                     "says when), 0 if never", 0 if age is None else 1)  # fmt: skip
        if age is not None:
            yield _gauge("loopcal_controller_config_calibration_age_seconds",
                         "seconds since loopcal last calibrated the controller config in force "
                         "(its provenance; absent if never)", age)  # fmt: skip
        for o in list(rec.analysis.observers):
            metrics = getattr(o, "metrics", None)
            if metrics is not None:
                yield from metrics()

    def _directory_bytes(self, directory: Path) -> float:
        measured, value = self._dir_bytes
        now = time.monotonic()
        if now - measured >= DIRECTORY_EVERY_S or measured == 0.0:
            try:
                value = sum(p.stat().st_size for p in find_recordings(directory))
            except (OSError, ValueError):
                value = self._dir_bytes[1]
            self._dir_bytes = (now, value)
        return float(value)


def _counter(name: str, doc: str, value: float) -> CounterMetricFamily:
    return CounterMetricFamily(name, doc, value=value)


def _gauge(name: str, doc: str, value: float, **labels: str) -> GaugeMetricFamily:
    if not labels:
        return GaugeMetricFamily(name, doc, value=value)
    fam = GaugeMetricFamily(name, doc, labels=list(labels))
    fam.add_metric(list(labels.values()), value)
    return fam


def _age_s(written_utc: object) -> float | None:
    """Seconds since ``written_utc`` (the provenance's, a string or a TOML datetime), or
    None if there is none or it is not a time."""
    from datetime import datetime

    try:
        if isinstance(written_utc, datetime):
            t_s = written_utc.timestamp()
        elif isinstance(written_utc, str):
            t_s = parse_time(written_utc) / 1e9
        else:
            return None
    except (ValueError, OverflowError):
        return None
    return max(0.0, time.time() - t_s)


#: the listen backlog of the metrics server: connections waiting for their thread (the
#: socketserver default of 5 timed out 16 of 600 concurrent scrapes)
LISTEN_BACKLOG = 1024

log = logging.getLogger(__name__)


class _Server(ThreadingWSGIServer):
    """prometheus-client's thread-per-request server, with a backlog for many scrapers."""

    request_queue_size = LISTEN_BACKLOG


class _Quiet(WSGIRequestHandler):
    def log_message(self, format: str, *args: object) -> None:  # noqa: A002 - the base's name
        pass  # a scrape every few seconds is no news


def exposed(host: str) -> str:
    """"" when ``host`` is a loopback address (only this machine reaches it), else what
    binding it exposes, in words ("every interface", "the interface of 10.0.0.5")."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError:
        return f"whatever {host} resolves to"
    addrs = {ipaddress.ip_address(i[4][0].split("%")[0]) for i in infos}
    if all(a.is_loopback for a in addrs):
        return ""
    if any(a.is_unspecified for a in addrs):
        return "every interface of this machine"
    return "the interface of " + ", ".join(sorted(map(str, addrs)))


class MetricsServer:
    """prometheus-client's WSGI app for a recorder's metrics on ``listen`` ("HOST:PORT"),
    served by a thread per request behind a backlog of :data:`LISTEN_BACKLOG`. Binds at
    once: a port that is taken is a SettingsError naming ``[metrics].listen``. An address
    that is not loopback is served, with a warning in the log saying what it exposes."""

    def __init__(self, recorder: MetricsSource, listen: str) -> None:
        host, port = parse_listen(listen)
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(RecorderCollector(recorder))
        try:
            family, _, _, _, sockaddr = socket.getaddrinfo(
                host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]  # fmt: skip
            server = type("_ServerOf", (_Server,), {"address_family": family})
            self._server = make_server(sockaddr[0], port, make_wsgi_app(self.registry), server,
                                       handler_class=_Quiet)  # fmt: skip
        except OSError as exc:
            raise SettingsError(
                f"cannot serve metrics on {listen}: {exc.strerror or exc}", "metrics_listen"
            ) from None
        self._thread = threading.Thread(target=self._server.serve_forever,
                                        name="loopcal-metrics", daemon=True)  # fmt: skip
        self._thread.start()
        self.url = f"http://{listen}/metrics"
        if what := exposed(host):
            log.warning("metrics on %s are served to %s, not only to this machine: anyone who "
                        "reaches it reads the recorder's state (files, scans, DAQ, health); "
                        "bind 127.0.0.1 and reach it through an SSH tunnel (docs/daemon.md)",
                        listen, what)  # fmt: skip

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
