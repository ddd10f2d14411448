"""Where a recorder that starts again carries on: the last scan already recorded in its
directory, read from whatever is intact of the newest recordings."""

from __future__ import annotations

import os

import numpy as np

from ..recording import RecordingError, find_recordings, read_recordings


def last_scan(
    directory: str | os.PathLike, problems: list[str] | None = None
) -> tuple[np.void, dict[str, dict[str, str]]] | None:
    """The newest scan recorded in a directory and its file's metadata, or None.

    For a recorder that starts again: it continues the power-on epoch and counts the scans
    lost while it was down. Files are tried newest first; a damaged one gives its last
    intact scan, an unreadable one is skipped. What was wrong with each file is appended to
    ``problems`` (one line each), for the recorder to report.
    """
    try:
        files = find_recordings(directory)
    except RecordingError as exc:
        if problems is not None:
            problems.append(str(exc))
        return None
    for path in reversed(files):
        try:
            rec = read_recordings([path])
        except RecordingError as exc:
            if problems is not None:
                problems.append(f"{exc}; skipped")
            continue
        if problems is not None:
            problems += rec.warnings
        if len(rec):
            return rec.scans[-1], rec.files[0].metadata
    return None


