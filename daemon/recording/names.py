"""File names of recordings: ``loopcal-YYYYmmddTHHMMSS.ffffffZ.mcap``, sorting by the UTC
time they start."""

from __future__ import annotations

import os
import re
import stat
from collections.abc import Iterable
from datetime import UTC, datetime
from pathlib import Path

from .errors import RecordingError
from .schemas import NS_PER_S

NAME_RE = re.compile(r"^loopcal-(\d{8}T\d{6}\.\d{6})Z\.mcap$")

# ---------------------------------------------------------------------------- names


def recording_name(utc_ns: int) -> str:
    """``loopcal-YYYYmmddTHHMMSS.ffffffZ.mcap``: names sort by the UTC time they start."""
    sec, ns = divmod(int(utc_ns), NS_PER_S)
    t = datetime.fromtimestamp(sec, UTC)
    return f"loopcal-{t:%Y%m%dT%H%M%S}.{ns // 1000:06d}Z.mcap"


def name_time_ns(path: str | os.PathLike) -> int | None:
    """The UTC start time a recording's name gives, ns, or None if not a recording name."""
    m = NAME_RE.match(Path(path).name)
    if not m:
        return None
    t = datetime.strptime(m.group(1), "%Y%m%dT%H%M%S.%f").replace(tzinfo=UTC)
    return int(t.timestamp()) * NS_PER_S + t.microsecond * 1000


def find_recordings(directory: str | os.PathLike) -> list[Path]:
    """The recordings in a directory (by their names), oldest first.

    Parameters
    ----------
    directory : str or os.PathLike
        The directory (not searched recursively).

    Returns
    -------
    list of pathlib.Path
        Its regular files named like recordings (``loopcal-YYYYmmddTHHMMSS.ffffffZ.mcap``),
        sorted by name, which is by the UTC time they were started; other files are
        ignored.

    Raises
    ------
    RecordingError
        If ``directory`` is not a directory.
    """
    d = Path(directory)
    if not d.is_dir():
        raise RecordingError(f"{d}: not a directory")
    return sorted(p for p in d.iterdir() if NAME_RE.match(p.name) and p.is_file())


def recording_paths(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """The recording files that files and directories name: a directory's recordings (by
    their names, oldest first), a file as named; each once, in the order named.

    Raises
    ------
    RecordingError
        For an empty path, a file that does not exist, or one that is not a regular file
        (a FIFO would block a reader, a device such as /dev/zero never ends)."""
    files: list[Path] = []
    for raw in paths:
        if os.fspath(raw) == "":
            raise RecordingError("an empty path names no recording")
        p = Path(raw)
        files += find_recordings(p) if p.is_dir() else [p]
    files = list(dict.fromkeys(files))  # a file named twice is read once
    for f in files:
        try:
            mode = f.stat().st_mode
        except FileNotFoundError:
            raise RecordingError(f"{f}: no such file") from None
        except OSError as exc:
            raise RecordingError(f"{f}: cannot read: {exc.strerror or exc}") from None
        if not stat.S_ISREG(mode):
            raise RecordingError(f"{f}: not a regular file ({_file_kind(mode)}): a recording "
                                 "is a file")  # fmt: skip
    return files


def _file_kind(mode: int) -> str:
    for test, kind in ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket")):  # fmt: skip
        if test(mode):
            return kind
    return "not a file"
