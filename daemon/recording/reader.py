"""read_recordings: one or many recording files (or directories of them) into numpy arrays,
oldest first, each scan once, with a line per damaged file."""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
from mcap.records import Statistics

from .. import scan_rows
from ..events import Event
from ..times import time_or
from .errors import RecordingError
from .filereader import FileReader
from .mcap_records import FOOTER_BYTES, MAGIC, RECORD_HEAD, is_ours, read_header
from .mcap_summary import read_statistics
from .names import recording_paths
from .recordingfile import RecordingFile
from .schemas import BLOCK_SPAN_NS, NS_PER_S


@dataclass
class Recording:
    """Scans and events of one or several recording files, oldest first.

    What :func:`read_recordings` returns. ``len(recording)`` is the number of scans.

    Attributes
    ----------
    scans : ndarray of SCAN_DTYPE, shape (n,)
        One row per scan (:data:`loopcal.daemon.scan_rows.SCAN_DTYPE`), each scan once (a scan
        in two files is kept once): files in the order of their first scan, each file's
        scans in (epoch, counter) order.
    events : list of Event
        The recorded events (:class:`loopcal.daemon.events.Event`) within the time window,
        in time order.
    files : list of RecordingFile
        One entry per file read, in the order of their first scan (files with no scan
        last); files wholly outside the time window are not read and not listed.
    since_ns : int or None, default None
        Where the time window began, ns since the Unix epoch: ``since``, or where
        ``last`` put it (None: no start).

    Notes
    -----
    The fields of a scan row (docs/recording.md): ``counter64`` (uint64, scans since the
    module's power-on, unwrapped), ``time64_us`` (uint64, device time of channel 1's
    conversion since power-on, µs, unwrapped), ``stamp_ns`` (int64, estimated acquisition
    time, ns since the Unix epoch, UTC), ``host_ns`` (int64, when the host received it),
    ``epoch`` (uint32, the module's power-on as recorded), ``missed`` (uint32, scans made
    just before this one that were never received), ``codes`` (uint16, shape (4,),
    channel 1..4 codes 0..4095), ``status`` (uint16: bits 0-3 rail, 4-7 sensor fault, 8
    overflow, 9 restart), and the bools ``restarted``, ``overflow``, ``time_measured``,
    ``status_measured``, ``from_fifo``.
    """

    scans: np.ndarray
    events: list[Event]
    files: list[RecordingFile]
    # where the time window began, ns: ``since``, or where ``last`` put it (None: no start)
    since_ns: int | None = None

    def __len__(self) -> int:
        return len(self.scans)

    @property
    def volts(self) -> np.ndarray:
        """Channel voltages, V, shape (n, 4), by the datasheet's mid-code reconstruction.

        ``V = (code + 0.5) * 20 / 4096 - 10`` of each scan's four codes
        (:func:`loopcal.drivers.ldq412.code_to_volts`), float64; computed on each access.
        """
        return scan_rows.volts(self.scans)

    @property
    def warnings(self) -> list[str]:
        """One line per damaged or partly read file, naming it and what was lost.

        A list of str: the :attr:`~loopcal.daemon.recording.recordingfile.RecordingFile.warning`
        of each file that did not read intact; empty when every file read intact.
        """
        return [f.warning for f in self.files if f.warning]

    def events_of(self, kind: str) -> list[Event]:
        """The events of one kind.

        Parameters
        ----------
        kind : str
            An event kind, e.g. ``"gap"``, ``"restart"``, ``"offset_drift"``
            (:data:`loopcal.daemon.events.KINDS`; docs/recording.md lists them).

        Returns
        -------
        list of Event
            Those of :attr:`events` with that kind, in time order (empty for a kind that
            never happened, or is not a kind at all).
        """
        return [e for e in self.events if e.kind == kind]


def _as_ns(t: int | float | datetime | None) -> int | None:
    if t is None:
        return None
    if isinstance(t, datetime):
        if t.tzinfo is None:
            raise ValueError(f"time {t} has no time zone; give UTC explicitly")
        return round(t.timestamp() * NS_PER_S)
    return int(t)


def identities(rows: np.ndarray) -> list[bytes]:
    """What makes a scan the same scan in two files: epoch, counter, device time, codes.

    Parameters
    ----------
    rows : ndarray of SCAN_DTYPE, shape (n,)
        Scan rows.

    Returns
    -------
    list of bytes
        One key per row (``epoch``, ``counter64``, ``time64_us`` and ``codes`` packed):
        equal keys are the same scan.
    """
    packed = np.zeros(len(rows), dtype=[("e", "<u4"), ("c", "<u8"), ("t", "<u8"),
                                        ("k", "<u2", (4,))])  # fmt: skip
    packed["e"], packed["c"] = rows["epoch"], rows["counter64"]
    packed["t"], packed["k"] = rows["time64_us"], rows["codes"]
    raw = packed.tobytes()
    k = packed.dtype.itemsize
    return [raw[i : i + k] for i in range(0, len(raw), k)]


def _key_range(rows: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    return ((int(rows["epoch"][0]), int(rows["counter64"][0])),
            (int(rows["epoch"][-1]), int(rows["counter64"][-1])))  # fmt: skip


def _read_tail_statistics(path: Path) -> Statistics | None:
    """The statistics record of a closed file, reading only its first and last bytes."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
            size = os.fstat(f.fileno()).st_size
            if size < 8 + FOOTER_BYTES + 8 or not head.startswith(MAGIC):
                return None
            f.seek(size - 8 - FOOTER_BYTES)
            footer = f.read(FOOTER_BYTES + 8)
            (start,) = struct.unpack_from("<Q", footer, RECORD_HEAD)
            if not 8 <= start <= size - 8 - FOOTER_BYTES:
                return None
            f.seek(start)
            tail = f.read()
    except (OSError, struct.error):
        return None
    header = read_header(memoryview(head))
    return read_statistics(memoryview(tail), strict=is_ours(header), base=start)


def message_time_range(path: Path) -> tuple[int, int] | None:
    """The first and last message log time of a closed file, from its statistics alone.

    Reads only the file's first and last bytes: footer, then summary offsets, then the
    statistics record, the summary checked by its CRC.

    Parameters
    ----------
    path : pathlib.Path
        A recording file.

    Returns
    -------
    tuple of 2 int, or None
        ``(first, last)`` message log times, ns since the Unix epoch; None if the file
        has no intact statistics record (not closed, damaged, unreadable, not MCAP) or no
        message.
    """
    stats = _read_tail_statistics(path)
    if stats is None or not stats.message_count:
        return None
    return stats.message_start_time, stats.message_end_time


def read_recordings(
    paths: str | os.PathLike | Iterable[str | os.PathLike],
    *,
    since: int | float | datetime | None = None,
    until: int | float | datetime | None = None,
    last: timedelta | None = None,
) -> Recording:
    """Load one or many recording files into numpy arrays.

    Whatever the bytes, it returns the scans that are intact, each once, and says in each
    file's :class:`RecordingFile` what could not be read (:attr:`Recording.warnings` has one
    line per damaged or partly read file). A file that was not closed (crash, power loss)
    is read up to its last intact chunk. Nothing that fails a check (a CRC, a length, an
    index offset) is returned.

    Parameters
    ----------
    paths : str, os.PathLike, or iterable of them
        Files, or directories (all recordings in them, by their names: see
        :func:`find_recordings`); a file named twice is read once. Files are put in time
        order by their first scan.
    since : int, float, datetime or None, default None
        Keep scans (and events) with ``since <= stamp``: ns since the Unix epoch, or an
        aware :class:`~datetime.datetime`.
    until : int, float, datetime or None, default None
        Keep scans (and events) with ``stamp < until``, likewise.
    last : datetime.timedelta or None, default None
        Instead of ``since``: keep the last ``last`` of them, from ``until - last``, or
        without ``until`` from ``last`` before the end of the recordings (the newest scan
        of a file that was not closed, the last message of a closed one, to the
        microsecond and included); :attr:`Recording.since_ns` says where.

    Returns
    -------
    Recording
        The scans, events and files (an empty one when the paths hold no recording).

    Raises
    ------
    RecordingError
        For a path that is empty, a file that is missing, unreadable or not a regular
        file, not MCAP at all, not a loopcal recording, or of another format version
        (the message names the file), or recordings that end at an impossible time.
    ValueError
        For an empty time window (``until`` not after ``since``), ``since`` and ``last``
        both given, a ``last`` that is not positive, or a datetime without a time zone.

    Notes
    -----
    Each file is read once: the closed ones' ends come from their statistics
    (:func:`message_time_range`; a file wholly outside the window is skipped), the
    others are read whole and cut in memory (their :class:`RecordingFile` then counts
    duplicates and undecodable messages of the whole file). A scan in two files (a polled
    scan read again after a recorder restart, or a copy) is kept once, by
    :func:`identities`.
    """
    lo, hi = _as_ns(since), _as_ns(until)
    if last is not None:
        if since is not None:
            raise ValueError("give since or last, not both")
        if last <= timedelta(0):
            raise ValueError(f"last ({last}) is not a positive duration")
    if lo is not None and hi is not None and hi <= lo:
        raise ValueError(
            f"empty time window: until ({time_or(hi)}) is not after since ({time_or(lo)})"
        )
    files = recording_paths([paths] if isinstance(paths, (str, os.PathLike)) else paths)
    windowed = lo is not None or hi is not None or last is not None
    spans = {path: message_time_range(path) for path in files} if windowed else {}
    read_whole: dict[Path, tuple[np.ndarray, RecordingFile, list[Event]]] = {}
    if last is not None and isinstance(until, datetime):
        lo = _as_ns(_before(until, last))
    elif last is not None and hi is not None:
        lo = hi - last // timedelta(microseconds=1) * 1000
    elif last is not None:  # the end: closed files' statistics, the others read whole
        read_whole = {p: FileReader(p, None, None).read() for p in files if spans[p] is None}
        ends = [span[1] for span in spans.values() if span is not None]
        ends += [int(r["stamp_ns"].max()) for r, _, _ in read_whole.values() if len(r)]
        if ends:
            lo = _as_ns(_before(_end_time(max(ends)), last))
    parts: list[tuple[np.ndarray, RecordingFile, list[Event]]] = []
    for path in files:
        if path in read_whole:
            parts.append(_cut(*read_whole[path], lo))
            continue
        span = spans.get(path)  # skip whole files outside the window cheaply
        if span is not None and not (
            (lo is None or span[1] + BLOCK_SPAN_NS >= lo) and (hi is None or span[0] < hi)
        ):
            continue
        parts.append(FileReader(path, lo, hi).read())
    parts.sort(key=lambda x: (x[1].first_stamp_ns is None, x[1].first_stamp_ns or 0, x[1].path))
    kept: list[np.ndarray] = []
    ranges: list[tuple[tuple[int, int], tuple[int, int]]] = []
    events: list[Event] = []
    for rows, info, evs in parts:
        if len(rows):
            lo_k, hi_k = _key_range(rows)
            overlapping = [i for i, (a, b) in enumerate(ranges) if a <= hi_k and lo_k <= b]
            if overlapping:  # the same scan in two files (copies, or a recorder restart)
                seen = {k for i in overlapping for k in identities(kept[i])}
                dup = np.fromiter((k in seen for k in identities(rows)), bool, len(rows))
                if dup.any():
                    rows = rows[~dup]
                    info.scans = len(rows)
            if len(rows):
                ranges.append(_key_range(rows))
                kept.append(rows)
        events += evs
    rows = np.concatenate(kept) if kept else scan_rows.empty()
    if lo is not None or hi is not None:
        events = [e for e in events if (lo is None or e.stamp_ns >= lo)
                  and (hi is None or e.stamp_ns < hi)]  # fmt: skip
    events.sort(key=lambda e: e.stamp_ns)
    return Recording(rows, events, [info for _, info, _ in parts], since_ns=lo)


def _end_time(end_ns: int) -> datetime:
    """Just after the newest stamp, to the microsecond: the end of the last ``last``."""
    try:
        return datetime.fromtimestamp(end_ns / 1e9, UTC) + timedelta(microseconds=1)
    except (OverflowError, OSError, ValueError):
        raise RecordingError(f"the recordings end at an impossible time ({end_ns} ns)") from None


def _before(end: datetime, last: timedelta) -> datetime:
    try:
        return end - last
    except OverflowError:
        return datetime.min.replace(tzinfo=UTC)


def _cut(
    rows: np.ndarray, info: RecordingFile, events: list[Event], since_ns: int | None
) -> tuple[np.ndarray, RecordingFile, list[Event]]:
    """A file read whole, as if read from ``since_ns`` on (its events are cut with the
    others')."""
    if since_ns is None:
        return rows, info, events
    # the file's own losses between two scans the cut keeps, not the cut's
    info.lost = [x for x in info.lost if x.after_ns >= since_ns and x.before_ns >= since_ns]
    rows = rows[rows["stamp_ns"] >= since_ns]
    info.scans = len(rows)
    info.first_stamp_ns = int(rows["stamp_ns"][0]) if len(rows) else None
    info.last_stamp_ns = int(rows["stamp_ns"][-1]) if len(rows) else None
    return rows, info, events
