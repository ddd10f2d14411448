"""Compacting the recorder's closed files in the background
(:mod:`loopcal.daemon.recording.compact`).

The writer hands every file it closes (a rotation) to the :class:`Compactor`, which has it
rewritten in chunks of a minute, so that reading the archive later is fast (a day in under
a second) while the file being written keeps its crash-safe one-second chunks. At start it
also takes every closed file of the directory that is not compact yet (files an older
loopcal compacted into chunks of 4 MiB, an hour's scans in one, included: they are
compacted again, once). The file being written is never touched; the retention holds the
directory's lock (:func:`~loopcal.daemon.recording.compact.directory_lock`) as a
compaction does when it replaces a file, so a file the retention deletes is not renamed
back into existence by a compaction that was reading it.

Each file is compacted by a child process (``loopcal compact --json FILE``, at the
compactor thread's low CPU priority, which it inherits), one at a time. Reading and
rewriting a file makes hundreds of thousands of small objects; in the recorder's own
process their freed memory stayed scattered over the interpreter's arenas and the recorder
grew by a few MB with each file (a single process writing and compacting 84,000-scan files:
108 MB after 3 files, 164 MB after 25; its live Python objects the same 23.7 MB throughout).
A child returns all of it when it exits, and a compaction that crashes or is killed costs
the recorder nothing but that file's compaction (the original stays as it was).

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
import json
import logging
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from ..recording import RecordingError, find_recordings
from ..recording.compact import Compacted, remove_stale_temporaries
from ..recording.names import name_time_ns
from ..recording.schemas import NS_PER_S

log = logging.getLogger(__name__)

NICE = 10  # the compaction thread's CPU priority (lower than the acquisition's)


#: seconds in a day
DAY_S = 86_400.0
DONE_KEPT = 1_000  # the files :attr:`Compactor.done` remembers
CHILD_TIMEOUT_S = 1800.0  # a compaction of an hour's file takes seconds


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


def compact_in_child(path: Path, *, drop_views: bool = False,
                     timeout_s: float = CHILD_TIMEOUT_S) -> Compacted:  # fmt: skip
    """:func:`~loopcal.daemon.recording.compact.compact` of ``path`` in a child process
    (``loopcal compact --json``, in a session of its own: a Ctrl-C meant for the recorder
    does not cut it short).

    Parameters
    ----------
    path : Path
        A closed recording.
    drop_views : bool, default False
        Leave out the per-scan views (``--drop-views``).
    timeout_s : float
        How long the child may take; then it is killed (its temporary file is removed by
        the next compaction of the file or of the directory).

    Returns
    -------
    Compacted
        What the child did, from its JSON report.

    Raises
    ------
    RuntimeError
        The child did not report (it crashed, was killed or timed out), naming why.
    """
    if not path.exists():  # the retention's, say
        return Compacted(path, False, "deleted before it was compacted")
    cmd = [sys.executable, "-m", "loopcal.daemon.cli", "compact", "--json", str(path)]
    if drop_views:
        cmd.insert(-1, "--drop-views")
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                              start_new_session=True, stdin=subprocess.DEVNULL)  # fmt: skip
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"the compaction took over {timeout_s:g} s and was stopped") from None
    try:
        [f] = json.loads(proc.stdout)["files"]
    except (ValueError, KeyError, TypeError):
        if not path.exists():
            return Compacted(path, False, "deleted while it was compacted")
        rc = proc.returncode
        why = proc.stderr.strip().splitlines()[-1:] or [
            f"killed by {signal.Signals(-rc).name}" if rc < 0 else f"exit status {rc}"]
        raise RuntimeError(f"the compaction did not finish: {why[0]}") from None
    return Compacted(path, bool(f["compacted"]), str(f["reason"]), int(f["chunks_before"]),
                     int(f["chunks_after"]), int(f["bytes_before"]), int(f["bytes_after"]),
                     failed=bool(f["failed"]), not_recording=bool(f["not_recording"]))  # fmt: skip


class Compactor:
    """A thread that compacts the files given to :meth:`submit`, one at a time.

    keep_views_days: called for the age in days (by a file's name) from which its views are
    left out (``math.inf``: never); a callable, so that a reload's new value holds."""

    def __init__(self, keep_views_days: Callable[[], float] = lambda: math.inf) -> None:
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
            result = compact_in_child(path, drop_views=drop)
        except Exception as exc:  # noqa: BLE001 - compaction is an optimisation: never fatal
            log.error("compacting %s failed (%s); the file is kept as it was", path, exc)
            self._settled.add(path)
            return
        if drop and result.reason != "being compacted by another process":
            self._settled.add(path)  # thinned, or nothing more to do to it
        if result.done:
            self.done.append(path)
            log.info("compacted %s%s: %d chunks -> %d, %d -> %d bytes", path.name,
                     " without its views" if drop else "", result.chunks_before,
                     result.chunks_after, result.bytes_before, result.bytes_after)  # fmt: skip
