"""The analysis thread: every scan the recorder receives also goes to its observers (live
analysis: the loop-closure health monitor, the technician's guidance), in a thread of their
own, so that neither reading the DAQ nor writing the recording ever waits for them.

An observer that fails is logged and dropped; the recording goes on.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from typing import Protocol

import numpy as np

from ..config.controller import ControllerConfig

log = logging.getLogger(__name__)

MAX_PENDING_BATCHES = 10_000  # beyond this (observers far behind) the oldest are dropped
#: seconds between two feeds: each feed has a fixed cost (the health monitor's still-pose
#: search, however few its new scans), so a second of scans at a time costs a controller
#: less (when chosen, bench_daemon with every feature on at 20 Hz: 1.57 % of a core against
#: 2.60 % fed every 0.25 s; figures of today in docs/tools.md); an alarm, a guidance line or
#: a health message is at most a second later (the live view's scans come from the writer)
PERIOD_S = 1.0


class Observer(Protocol):
    """What the recorder feeds: ``feed`` gets every scan row (SCAN_DTYPE) in order, from the
    analysis thread; ``status`` is a part of the status line; ``reload`` gets the controller
    config a reload put in force (between two feeds)."""

    name: str

    def feed(self, rows: np.ndarray) -> None: ...

    def status(self) -> str: ...

    def reload(self, controller: ControllerConfig) -> None: ...


class AnalysisThread:
    """Feeds queued scan rows to the observers, in order, about every PERIOD_S seconds."""

    def __init__(self, observers: list[Observer]) -> None:
        self.observers = list(observers)
        self._pending: deque[np.ndarray] = deque(maxlen=MAX_PENDING_BATCHES)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="loopcal-analysis", daemon=True)
        self._started = self._running = False

    def start(self) -> AnalysisThread:
        with self._lock:
            self._started = True
            run = self._running = bool(self.observers)
        if run:
            self._thread.start()
        return self

    def add(self, observer: Observer) -> None:
        """Feed ``observer`` too from the next scans on (a session started while recording;
        the thread starts now if it had nothing to feed)."""
        with self._lock:
            self.observers.append(observer)
            run = self._started and not self._running and not self._stop.is_set()
            self._running = self._running or run
        if run:
            self._thread.start()

    def remove(self, observer: Observer) -> None:
        """Feed ``observer`` no more: once this returns, no feed of it is under way."""
        with self._lock:
            if observer in self.observers:
                self.observers.remove(observer)

    def put(self, rows: np.ndarray) -> None:
        """Queue scan rows (never blocks)."""
        if self.observers and len(rows):
            self._pending.append(rows)

    def stop(self, timeout: float = 5.0) -> None:
        """Feed what is queued, then stop."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def reload(self, controller: ControllerConfig) -> None:
        """Give every observer the new controller config, between two feeds."""
        with self._lock:
            for o in self.observers:
                o.reload(controller)

    def status(self) -> list[str]:
        with self._lock:
            return [o.status() for o in self.observers]

    def _run(self) -> None:
        while True:
            stopping = self._stop.is_set()
            batches = []
            while self._pending:
                batches.append(self._pending.popleft())
            if batches:
                rows = np.concatenate(batches)
                with self._lock:
                    for o in list(self.observers):
                        try:
                            o.feed(rows)
                        except Exception:  # noqa: BLE001 - an observer never stops recording
                            log.exception("%s failed and is switched off", o.name)
                            self.observers.remove(o)
            if stopping:
                return
            self._wake.wait(PERIOD_S)
            self._wake.clear()
