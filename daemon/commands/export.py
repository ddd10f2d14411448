"""``loopcal export REC|DIR ... --out DIR [--controller-config PATH] [--json]``: a recording
for Foxglove, with every view, made again from the raw scans of each file.

``loopcal compact --drop-views`` (or the daemon's ``[recording].keep_views_days``) leaves out
the per-scan views of old files (/joint/state, /plate/transform): every raw scan and event
stays. This command writes each given file anew into the directory ``--out`` (created if
missing), under the same name, as the recorder writes a file: the raw scans bit for bit, the
events, and the views (/joint/state of every scan, /plate/transform of every scan with a
pose, /plate/scene), computed at the parameters of the controller config the file records
in its ``controller_config`` metadata record, or at those of ``--controller-config PATH``
(a controller config TOML) when given. A file with its views works as well: its views are
made again, at the parameters chosen. The metadata records are the original's: the
``loopcal`` record says the format as written and the version of the loopcal that wrote the
file (the recorder's, if another, as ``recorded_version``) and gains ``exported_from`` (the
source file) and ``exported_utc``; the ``controller_config`` record is the one the views
were computed with. The file is written to ``.NAME.export.tmp`` in ``--out`` and renamed to
its name only when complete and fsynced: a killed export leaves no half file under the real
name (its temporary file is removed by the next export of that file).

Never overwrites: an output file that already exists is refused before anything is
written. A damaged file is exported with what it holds, its reader's warning printed. A
file whose controller config record cannot give the 20 parameters (a missing or
incomplete record) is not exported unless ``--controller-config`` is given; the others
still are.

``--json``: one object, ``{"files": [{"path", "out", "scans", "views", "warning",
"error"}], "failed"}``; ``out`` is null for a file not exported, ``views`` the number of
messages of each view topic written.

Exit status 0 when every file was exported whole, 1 when a file could not be exported or
was damaged (exported with what it holds), 2 for bad input, with a line ``loopcal export:
error: ...`` naming it: an empty path, a path that does not exist, one that is not a regular
file (a FIFO, a device), a directory holding no recordings, a file that is not a recording,
an ``--out`` that is not a directory, an output file that exists, a controller config that
cannot be read.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from ..arguments import add_recordings_argument, path_argument
from ..config.controller import (
    ControllerConfig,
    load_controller_config,
    params_from_metadata,
)
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
from ..recording.compact import recordings_named
from ..recording.schemas import NS_PER_S
from ..times import now_text
from ..version import loopcal_version
from .errors import CommandError

#: scan time fed to the writer at a time (one write: one chunk of scans, one of views)
BATCH_NS = 60 * NS_PER_S
#: the ``loopcal`` record's keys that describe a file as compacted, not as written
_COMPACTION_KEYS = ("views", "scans", "views_dropped_utc", "compacted_utc", "chunk_span_s")
#: the topics of the views, in the order the JSON lists them
_VIEW_TOPICS = (TOPIC_STATE, TOPIC_TRANSFORM, TOPIC_SCENE)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_recordings_argument(p)
    p.add_argument("--out", type=path_argument, required=True, metavar="DIR",
                   help="the directory to write the exported files to, each under its "
                        "original's name (created if missing; no file in it is "
                        "replaced)")  # fmt: skip
    p.add_argument("--controller-config", type=path_argument, metavar="PATH",
                   help="compute the views at this controller config's parameters instead "
                        "of those each file records")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help="one JSON object on stdout: what was done with each file")  # fmt: skip


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
    """Export the recording ``path`` to the new file ``target`` (see the module docstring).
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


def run(args: argparse.Namespace) -> int:
    try:
        files = recordings_named(args.recordings)
        out: Path = args.out
        if os.path.lexists(out) and not out.is_dir():
            raise CommandError(f"--out {out}: exists and is not a directory")
        config = None
        if args.controller_config is not None:
            config = load_controller_config(args.controller_config)
        targets: dict[Path, Path] = {}
        for f in files:
            target = out / f.name
            if target in targets:
                raise CommandError(f"{f} and {targets[target]}: both would be exported to "
                                   f"{target}")  # fmt: skip
            if os.path.lexists(target):
                raise CommandError(f"{target}: exists")
            targets[target] = f
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CommandError(exc) from None
    results: list[Exported] = []
    for target, f in targets.items():
        try:
            r = export_file(f, target, config)
        except FileExistsError:
            r = Exported(f, error=f"{target}: exists (created meanwhile; left as it is)")
        except OSError as exc:
            r = Exported(f, error=f"{f}: not exported: {exc.strerror or exc}")
        results.append(r)
        if args.json:
            continue
        if r.out is not None:
            views = ", ".join(f"{t} {n:,}" for t, n in r.views.items())
            print(f"{f} -> {r.out}: {r.scans:,} scans; views: {views}")
        if r.warning:
            print(f"loopcal export: warning: {r.warning}", file=sys.stderr)
        if r.error and not r.not_recording:
            print(r.error, file=sys.stderr)
    failed = sum(r.failed for r in results)
    if args.json:
        print(json.dumps({"files": [r.as_json() for r in results], "failed": failed}, indent=1))
    strangers = [r for r in results if r.not_recording]
    not_whole = failed - len(strangers)
    if not_whole and not args.json:
        print(f"loopcal export: {not_whole} file(s) not exported or damaged", file=sys.stderr)
    if strangers:  # bad input found in a directory: each named, the others exported
        raise CommandError("\n".join(r.error for r in strangers))
    return 1 if failed else 0
