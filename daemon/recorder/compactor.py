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
"""

from __future__ import annotations

import logging
import os
import queue
import threading
from pathlib import Path

from ..recording import RecordingError, find_recordings
from ..recording.compact import compact, remove_stale_temporaries

log = logging.getLogger(__name__)

NICE = 10  # the compaction thread's CPU priority (lower than the acquisition's)


class Compactor:
    """A thread that compacts the files given to :meth:`submit`, one at a time."""

    def __init__(self) -> None:
        self.lock = threading.Lock()  # held while a file is replaced, and by the retention
        self._queue: queue.Queue[Path | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="loopcal-compact", daemon=True)
        self.done: list[Path] = []

    def start(self, directory: Path | None = None) -> Compactor:
        """Start the thread; queue the closed files of ``directory`` not compact yet."""
        if directory is not None and directory.is_dir():
            remove_stale_temporaries(directory)
            try:
                for path in find_recordings(directory):
                    self.submit(path)
            except RecordingError:
                pass
        self._thread.start()
        return self

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
            try:
                result = compact(path, replace_lock=self.lock)
            except Exception:  # noqa: BLE001 - compaction is an optimisation: never fatal
                log.exception("compacting %s failed; the file is kept as it was", path)
                continue
            if result.done:
                self.done.append(path)
                log.info("compacted %s: %d chunks -> %d, %d -> %d bytes", path.name,
                         result.chunks_before, result.chunks_after, result.bytes_before,
                         result.bytes_after)  # fmt: skip
