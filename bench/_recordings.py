"""Recordings for the bench scripts as the daemon keeps them."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

from loopcal.daemon.recording import find_recordings
from loopcal.daemon.recording.compact import compact


def compacted_copy(
    directory: Path, kept: Path | None = None, *, reuse: bool = False
) -> tuple[Path, float]:
    """A copy of the recording ``directory`` as the daemon keeps it: every closed file
    compacted, as after its rotation. The copy goes to ``kept`` (by default
    DIRECTORY-compacted beside it), replacing one already there, or, with ``reuse``, one
    already there is taken as it is. Returns the copy and the seconds compacting took (0
    for a copy reused)."""
    kept = kept or directory.with_name(directory.name + "-compacted")
    if kept.is_dir():
        if reuse and find_recordings(kept):
            return kept, 0.0
        if not reuse:
            shutil.rmtree(kept)
    shutil.copytree(directory, kept, dirs_exist_ok=True)
    t = time.perf_counter()
    for f in find_recordings(kept):
        if not compact(f).done:
            raise SystemExit(f"could not compact {f}")
    return kept, time.perf_counter() - t
