"""``loopcal export``'s work on one file: a recording written anew, as the recorder writes a
file, with every view made again from its raw scans (:func:`export_file`; the command,
:mod:`loopcal.daemon.commands.export`, says what it does and checks its input).

Apart from the command's module so that ``loopcal export --help`` does not wait for numpy
and mcap.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from ..config.controller import ControllerConfig, params_from_metadata
from ..config.durable import fsync_dir, step
from ..events import Event
from ..recording import (
    FORMAT_VERSION,
    TOPIC_SCENE,
    TOPIC_STATE,
    TOPIC_TRANSFORM,
    RecordingError,
    RecordingWriter,
    read_recordings,
)
from ..recording.schemas import NS_PER_S
from ..times import now_text
from ..version import loopcal_version

#: scan time fed to the writer at a time (one write: one chunk of scans, one of views)
BATCH_NS = 60 * NS_PER_S
#: the ``loopcal`` record's keys that describe a file as compacted, not as written
_COMPACTION_KEYS = ("views", "scans", "views_dropped_utc", "compacted_utc", "chunk_span_s")
#: the topics of the views, in the order the JSON lists them
_VIEW_TOPICS = (TOPIC_STATE, TOPIC_TRANSFORM, TOPIC_SCENE)


@dataclass
class Exported:
    """What became of one file: exported to ``out`` (None: not exported, ``error`` says
    why; ``not_recording``: it is not a recording, which is bad input), its scans and view
    messages written, its reader's warning (damage)."""

    path: Path
    out: Path | None = None
    scans: int = 0
    views: dict[str, int] = field(default_factory=dict)
    warning: str = ""
    error: str = ""
    not_recording: bool = False

    @property
    def failed(self) -> bool:
        return bool(self.error or self.warning)

    def as_json(self) -> dict[str, object]:
        return {"path": str(self.path), "out": None if self.out is None else str(self.out),
                "scans": self.scans, "views": self.views, "warning": self.warning or None,
                "error": self.error or None}  # fmt: skip


def _metadata(
    original: dict[str, dict[str, str]], controller: dict[str, str], source: Path
) -> dict[str, dict[str, str]]:
    """The exported file's metadata records: the original's, the ``loopcal`` record as of a
    file as written (plus where and when it was exported from), ``controller`` as used."""
    loopcal = {k: v for k, v in original.get("loopcal", {}).items() if k not in _COMPACTION_KEYS}
    loopcal["format"] = FORMAT_VERSION
    # the file's header names the loopcal that wrote it, and ``loopcal verify`` holds the
    # record's version to it: the recorder's version, if another, stays as recorded_version
    recorded = loopcal.get("version")
    loopcal["version"] = loopcal_version()
    if recorded and recorded != loopcal["version"]:
        loopcal["recorded_version"] = recorded
    loopcal["exported_from"] = os.path.abspath(source)
    loopcal["exported_utc"] = now_text()
    out = {"loopcal": loopcal}
    for name, record in original.items():
        if name != "loopcal":
            out[name] = dict(record)
    out["controller_config"] = dict(controller)
    return out


def _batches(rows: np.ndarray, events: list[Event]) -> list[tuple[np.ndarray, list[Event]]]:
    """``rows`` in batches of :data:`BATCH_NS` of scan time from the first scan, each with
    the events of its time (from its first scan to the next batch's; those before the first
    scan go with the first batch, those after the last with the last)."""
    if not len(rows):
        return [(rows, list(events))] if events else []
    stamps = rows["stamp_ns"].astype(np.int64)
    cuts = np.flatnonzero(np.diff((stamps - stamps[0]) // BATCH_NS)) + 1
    starts = np.concatenate([[0], cuts])
    batches: list[tuple[np.ndarray, list[Event]]] = [(part, []) for part in np.split(rows, cuts)]
    firsts = stamps[starts]
    for ev in events:
        k = int(np.searchsorted(firsts, ev.stamp_ns, side="right")) - 1
        batches[min(max(k, 0), len(batches) - 1)][1].append(ev)
    return batches


def _view_counts(path: Path) -> dict[str, int]:
    """Messages of each view topic in the closed file ``path``, by its statistics."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    counts = {t: 0 for t in _VIEW_TOPICS}
    if summary is None or summary.statistics is None:
        return counts
    for cid, n in summary.statistics.channel_message_counts.items():
        ch = summary.channels.get(cid)
        if ch is not None and ch.topic in counts:
            counts[ch.topic] += n
    return counts


def _place(tmp: Path, target: Path) -> None:
    """Give the complete ``tmp`` its name ``target`` atomically, never replacing a file
    that took the name meanwhile (a hard link, which fails when the name exists; a rename
    on file systems without links)."""
    try:
        os.link(tmp, target)
    except FileExistsError:
        raise
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EMLINK):
            raise
        if os.path.lexists(target):
            raise FileExistsError(errno.EEXIST, "exists", str(target)) from None
        os.rename(tmp, target)
    else:
        tmp.unlink()


def export_file(path: Path, target: Path, config: ControllerConfig | None) -> Exported:
    """Export the recording ``path`` to the new file ``target`` (as ``loopcal export``'s help
    says: :mod:`loopcal.daemon.commands.export`).
    Raises OSError if the disk refuses (nothing is then left under ``target``'s name)."""
    try:
        recording = read_recordings(path)
    except RecordingError as exc:
        return Exported(path, error=str(exc), not_recording=True)
    info = recording.files[0] if recording.files else None
    original = info.metadata if info is not None else {}
    warning = info.warning if info is not None else ""
    if config is not None:
        params, controller = config.params, config.as_metadata()
    else:
        controller = original.get("controller_config", {})
        params, why = params_from_metadata(controller)
        if params is None:
            return Exported(path, scans=len(recording.scans), warning=warning,
                            error=f"{path}: not exported: {why}; give the parameters with "
                                  "--controller-config PATH")  # fmt: skip
    tmp = target.with_name(f".{target.name}.export.tmp")
    tmp.unlink(missing_ok=True)  # left by an export that was killed
    writer = RecordingWriter(tmp, metadata=_metadata(original, controller, path), params=params,
                             fsync=False)  # fmt: skip
    try:
        for rows, events in _batches(recording.scans, recording.events):
            writer.write(rows, events)
        writer.close()
        fd = os.open(tmp, os.O_RDONLY | os.O_CLOEXEC)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        views = _view_counts(tmp)
        step("export-written")  # tests kill it here: the file complete, not yet named
        _place(tmp, target)
        fsync_dir(target.parent)
    except BaseException:
        writer.abandon()
        tmp.unlink(missing_ok=True)
        raise
    if writer.views_error:
        more = f"{path}: no pose could be computed: {writer.views_error}"
        warning = f"{warning}; {more}" if warning else more
    return Exported(path, target, writer.scans_written, views, warning)
