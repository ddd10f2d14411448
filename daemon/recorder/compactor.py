"""Compacting the recorder's closed files in the background
(:mod:`loopcal.daemon.recording.compact`).

The writer hands every file it closes (a rotation) to the :class:`Compactor`, which rewrites
it in chunks of a minute in a thread of its own at a low CPU priority, so that reading the
archive later is fast (a day in under a second) while the file being written keeps its
crash-safe one-second chunks. At start it also takes every closed file of the directory
that is not compact yet (files an older loopcal compacted into chunks of 4 MiB, an hour's
scans in one, included: they are compacted again, once). The file being written is never
touched; the retention and the compactor share :attr:`Compactor.lock`, so a file the
retention deletes is not renamed back into existence by a compaction that was reading it.

Views: a file started ``keep_views_days`` ago or more (by the UTC time in its name) is
compacted without its per-scan views (``compact(..., drop_views=True)``: every raw scan and
event stays, about a twentieth of the bytes). Files cross that age while the daemon runs for
months, so after each file it is handed the compactor looks over the directory again for
files whose views have expired (their names alone: a file it has already thinned, or given
up on, is not opened again).
"""

from __future__ import annotations

import collections
import ctypes
import logging
import math
import os
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path

from ..recording import RecordingError, find_recordings
from ..recording.compact import compact, remove_stale_temporaries
from ..recording.names import name_time_ns
from ..recording.schemas import NS_PER_S

log = logging.getLogger(__name__)

NICE = 10  # the compaction thread's CPU priority (lower than the acquisition's)


#: seconds in a day
DAY_S = 86_400.0
DONE_KEPT = 1_000  # the files :attr:`Compactor.done` remembers


def release_free_heap() -> bool:
    """Give the C heap's free pages back to the system (glibc's ``malloc_trim(0)``; False
    where the C library has none).

    A compaction reads a file's messages and lets them go: the freed memory stays with the
    process, scattered between what is still in use, and a daemon that runs for months
    would keep the largest such peak. Trimming after each file keeps its resident memory
    at what it uses (bench/bench_daemon.py --part memory)."""
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (AttributeError, OSError):
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True


class Compactor:
    """A thread that compacts the files given to :meth:`submit`, one at a time.

    keep_views_days: called for the age in days (by a file's name) from which its views are
    left out (``math.inf``: never); a callable, so that a reload's new value holds."""

    def __init__(self, keep_views_days: Callable[[], float] = lambda: math.inf) -> None:
        self.lock = threading.Lock()  # held while a file is replaced, and by the retention
        self._queue: queue.Queue[Path | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="loopcal-compact", daemon=True)
        self._keep_views_days = keep_views_days
        self._directory: Path | None = None
        #: files whose views are gone, or that could not be thinned: not looked at again
        #: (forgotten once the retention has removed them: the set stays the directory's size)
        self._settled: set[Path] = set()
        #: the latest files compacted, newest last (bounded: the daemon runs for months)
        self.done: collections.deque[Path] = collections.deque(maxlen=DONE_KEPT)

    def start(self, directory: Path | None = None) -> Compactor:
        """Start the thread; queue the closed files of ``directory`` not compact yet."""
        if directory is not None and directory.is_dir():
            self._directory = directory
            remove_stale_temporaries(directory)
            try:
                for path in find_recordings(directory):
                    self.submit(path)
            except RecordingError:
                pass
        self._thread.start()
        return self

    def views_expired(self, path: Path, now_ns: int | None = None) -> bool:
        """Whether ``path`` started ``keep_views_days`` ago or more (by its name; a name
        without a time never expires)."""
        days = self._keep_views_days()
        started = name_time_ns(path)
        if started is None or not math.isfinite(days):
            return False
        now = time.time_ns() if now_ns is None else now_ns
        return now - started >= days * DAY_S * NS_PER_S

    def _expired_in_directory(self) -> list[Path]:
        if self._directory is None or not math.isfinite(self._keep_views_days()):
            return []
        try:
            paths = find_recordings(self._directory)
        except (RecordingError, OSError):
            return []
        self._settled.intersection_update(paths)
        # the newest file is the one being written: never touched (it is not closed)
        return [p for p in paths[:-1] if p not in self._settled and self.views_expired(p)]

    def submit(self, path: Path) -> None:
        """Compact ``path`` (a closed recording) when the thread gets to it."""
        self._queue.put(path)

    def stop(self, timeout: float = 10.0) -> None:
        """Finish the file under way (a compaction is never left half done by choice)."""
        self._queue.put(None)
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), NICE)
        except (OSError, AttributeError):
            pass
        while (path := self._queue.get()) is not None:
            self._compact(path)
            if self._queue.empty():  # files whose views expired since the last look
                for old in self._expired_in_directory():
                    if not self._queue.empty():  # a new file, or stop: that first
                        break
                    self._compact(old)
            release_free_heap()

    def _compact(self, path: Path) -> None:
        drop = self.views_expired(path)
        try:
            result = compact(path, drop_views=drop, replace_lock=self.lock)
        except Exception:  # noqa: BLE001 - compaction is an optimisation: never fatal
            log.exception("compacting %s failed; the file is kept as it was", path)
            self._settled.add(path)
            return
        if drop and result.reason != "being compacted by another process":
            self._settled.add(path)  # thinned, or nothing more to do to it
        if result.done:
            self.done.append(path)
            log.info("compacted %s%s: %d chunks -> %d, %d -> %d bytes", path.name,
                     " without its views" if drop else "", result.chunks_before,
                     result.chunks_after, result.bytes_before, result.bytes_after)  # fmt: skip
