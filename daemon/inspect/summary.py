"""What recordings hold, summed up file by file (``loopcal info``, ``loopcal fleet info``):
time span, scans counted once, rate, missed scans and gaps, the module's power-on and its
restarts, events by kind, still poses, the controller configs in force, damage. Memory stays
that of one file.

Damage is what the reader found (scans missing, damaged parts it read around) and what
checking every record of the file found (:func:`~loopcal.daemon.recording.verify.verify_file`:
the views' chunks too, the indexes, the statistics): each damaged item is named with its byte
offset, the topics of its messages and their time span. ``damaged: none`` only when every
record of every file checked out and the reader lost nothing.

A module's first scan after power-on carries the restart flag. On the recordings' first scan,
in the first power-on the recorder saw (epoch 0), it says when the module was powered on, not
that it restarted while recorded: restarts are counted after it."""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.recfunctions import repack_fields

from ..recording import RecordingError, read_recordings
from ..recording.names import recording_paths
from ..recording.reader import identities
from ..recording.verify import verify_file
from ..scan_rows import scan_rate_hz
from ..times import parse_time, time_json, time_text
from ..worker.recorded_poses import completed_poses

_TAIL = 512  # scans of a file's end compared with the next file's start


@dataclass
class Summary:
    """What the recordings hold (see the module docstring); built file by file."""

    files: list[dict[str, Any]] = field(default_factory=list)
    scans: int = 0
    start_ns: int | None = None
    end_ns: int | None = None
    missed: int = 0
    gaps: int = 0
    restarts: int = 0
    powered_on_ns: int | None = None  # the first scan, if it is the module's power-on
    power_ons: set[tuple[str, int]] = field(default_factory=set)
    rates: list[tuple[int, float]] = field(default_factory=list)  # (scans, Hz) per file
    events: Counter = field(default_factory=Counter)
    poses: int | None = 0
    configs: dict[str, dict[str, Any]] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    #: every damaged item of every file (its path under "file"), as verify_file found them
    damaged: list[dict[str, Any]] = field(default_factory=list)
    scans_lost: int = 0  # scans known to be missing (counter gaps no ``missed`` explains)
    _seen_events: set[tuple[int, str, str]] = field(default_factory=set)
    _last_key: tuple[int, int] | None = None  # (epoch, counter64) of the last scan counted
    _tail: set[bytes] = field(default_factory=set)  # the identities of the last file's tail
    _digests: set[str] = field(default_factory=set)  # of every file's scans: copies count once
    #: the scans after the last still pose counted, searched again with the next file's (a
    #: pose across a file boundary is one pose, as the health monitor sees it)
    _pose_tail: np.ndarray | None = None

    def add(self, path: Path, *, poses: bool) -> None:
        rec = read_recordings(path)
        info = rec.files[0]
        rows = rec.scans
        digest = hashlib.sha256(repack_fields(rows).tobytes()).hexdigest()
        if digest in self._digests:
            rows = rows[:0]  # a copy of a file already counted
        self._digests.add(digest)
        if len(rows) and self._last_key is not None:
            # a scan at or before the last one counted may repeat it (a copy of a file, a
            # recorder that read a scan again after a restart): once
            e, c = rows["epoch"].astype(np.int64), rows["counter64"]
            le, lc = self._last_key
            early = np.flatnonzero((e < le) | ((e == le) & (c <= lc)))
            if len(early):
                seen = identities(rows[early])
                drop = early[[k in self._tail for k in seen]]
                rows = np.delete(rows, drop)
        if len(rows):
            self._last_key = (int(rows["epoch"][-1]), int(rows["counter64"][-1]))
            self._tail = set(identities(rows[-_TAIL:]))
        size = path.stat().st_size
        checked = verify_file(path)
        damaged = [d.as_json() for d in checked.damaged]
        self.damaged += [{"file": str(path), **d} for d in damaged]
        self.scans_lost += info.lost_scans
        self.files.append({
            "path": str(path), "bytes": size, "complete": info.complete,
            "views": info.metadata.get("loopcal", {}).get("views") != "dropped",
            "scans": len(rows),
            "start_utc": time_json(info.first_stamp_ns), "end_utc": time_json(info.last_stamp_ns),
            "note": info.note or None, "warning": info.warning or None,
            "records_checked": checked.records, "damaged": damaged,
            "damage": [d.text() for d in checked.damaged], "scans_lost": info.lost_scans,
        })  # fmt: skip
        if info.warning:
            self.warnings.append(info.warning)
        if info.note:
            self.notes.append(f"{path.name}: {info.note}")
        for e in rec.events:
            key = (e.stamp_ns, e.kind, e.message)
            if key not in self._seen_events:
                self._seen_events.add(key)
                self.events[e.kind] += 1
        cfg = info.metadata.get("controller_config", {})
        if cfg:
            key = cfg.get("sha256", "") or "reference geometry"
            entry = self.configs.setdefault(key, _config_entry(cfg))
            entry["files"] += 1
        if not len(rows):
            return
        opening = self.scans == 0  # these are the recordings' first scans
        self.scans += len(rows)
        first, last = int(rows["stamp_ns"][0]), int(rows["stamp_ns"][-1])
        self.start_ns = first if self.start_ns is None else min(self.start_ns, first)
        self.end_ns = last if self.end_ns is None else max(self.end_ns, last)
        self.missed += int(rows["missed"].sum())
        self.gaps += int(np.count_nonzero((rows["missed"] > 0) & ~rows["restarted"]))
        restarted = rows["restarted"]
        if opening and restarted[0] and rows["epoch"][0] == 0:
            self.powered_on_ns = first
            restarted = restarted[1:]
        self.restarts += int(np.count_nonzero(restarted))
        serial = info.metadata.get("device", {}).get("serial", "")
        self.power_ons |= {(serial, int(e)) for e in np.unique(rows["epoch"])}
        self.rates.append((len(rows), scan_rate_hz(rows)))
        if poses and self.poses is not None:
            buf = rows if self._pose_tail is None else np.concatenate([self._pose_tail, rows])
            _, done, keep_from = completed_poses(buf)
            self.poses += len(done)
            self._pose_tail = buf[keep_from:].copy()

    def finish(self) -> None:
        """The recordings end: the still pose they end in counts too."""
        if self.poses is not None and self._pose_tail is not None and len(self._pose_tail):
            self.poses += len(completed_poses(self._pose_tail, final=True)[1])
        self._pose_tail = None

    @property
    def scan_rate_hz(self) -> float | None:
        if not self.rates:
            return None
        n = np.array([r[0] for r in self.rates], dtype=float)
        hz = np.array([r[1] for r in self.rates])
        return float(np.sum(n * hz) / n.sum())

    def as_json(self) -> dict[str, Any]:
        span = (self.end_ns - self.start_ns) / 1e9 if self.start_ns is not None else 0.0
        return {
            "files": self.files,
            "bytes": sum(f["bytes"] for f in self.files),
            "scans": self.scans,
            "start_utc": time_json(self.start_ns),
            "end_utc": time_json(self.end_ns),
            "duration_s": round(span, 3),
            "scan_rate_hz": None if self.scan_rate_hz is None else round(self.scan_rate_hz, 4),
            "missed": self.missed,
            "gaps": self.gaps,
            "powered_on_utc": time_json(self.powered_on_ns),
            "restarts": self.restarts,
            "power_ons": len(self.power_ons),
            "events": dict(sorted(self.events.items())),
            "poses": self.poses,
            "controller_configs": list(self.configs.values()),
            "warnings": self.warnings,
            "notes": self.notes,
            "damaged": self.damaged,
            "scans_lost": self.scans_lost,
        }


def _config_entry(cfg: dict[str, str]) -> dict[str, Any]:
    prov: dict[str, Any] = {}
    if cfg.get("provenance"):
        try:
            prov = json.loads(cfg["provenance"])
        except ValueError:
            prov = {}
    return {
        "path": cfg.get("path") or None,
        "sha256": cfg.get("sha256") or None,
        "calibrated_utc": _one_spelling(prov.get("written_utc")),
        "method": prov.get("method"),
        "files": 0,
    }


def _one_spelling(text: object) -> str | None:
    """A time a config's provenance gives (any version's spelling) in the one loopcal
    prints; kept as it is if it is not a time (shown, not hidden)."""
    if not isinstance(text, str):
        return None
    try:
        return time_text(parse_time(text))
    except ValueError:
        return text


def collect(paths: list[Path], *, poses: bool = True) -> Summary:
    """The summary of recording files and directories (files in time order by name)."""
    files = recording_paths(paths)
    if not files:
        raise RecordingError(f"{', '.join(map(str, paths))}: no recordings (loopcal-*.mcap)")
    out = Summary(poses=0 if poses else None)
    for f in files:
        out.add(f, poses=poses)
    out.finish()
    return out


def render(doc: dict[str, Any]) -> list[str]:
    """The summary for people."""
    hours, rem = divmod(int(doc["duration_s"]), 3600)
    on = doc["powered_on_utc"]
    powered_on = f"{on} (the first scan)" if on else "before the first scan"
    since = " since" if on else ""
    lines = [
        f"files:      {len(doc['files'])} ({doc['bytes'] / 1e6:,.1f} MB)",
        f"time span:  {doc['start_utc'] or '-'} to {doc['end_utc'] or '-'} "
        f"({hours} h {rem // 60} min {rem % 60} s)",
        f"scans:      {doc['scans']:,}"
        + (f" at {doc['scan_rate_hz']:.3f} Hz" if doc["scan_rate_hz"] else ""),
        f"missed:     {doc['missed']:,} scans in {doc['gaps']} gap(s)",
        f"powered on: {powered_on}",
        f"restarts:   {doc['restarts']}{since} (power-ons seen: {doc['power_ons']})",
        "events:     " + (", ".join(f"{k} {n}" for k, n in doc["events"].items()) or "none"),
    ]
    if doc["poses"] is not None:
        lines.append(f"still poses: {doc['poses']:,}")
    for c in doc["controller_configs"]:
        how = (f", calibrated {c['calibrated_utc']} ({c['method']})" if c["calibrated_utc"]
               else ", never calibrated by loopcal")  # fmt: skip
        lines.append(f"controller config: {c['path'] or 'reference geometry'} "
                     f"sha256 {(c['sha256'] or '-')[:12]}{how}; {c['files']} file(s)")  # fmt: skip
    lines += damage_lines(doc)
    lines.append("files:")
    for f in doc["files"]:
        state = "closed" if f["complete"] else "not closed"
        if not f.get("views", True):
            state += ", views left out (loopcal export makes them)"
        lines.append(f"  {Path(f['path']).name}  {f['start_utc'] or '-'} to "
                     f"{f['end_utc'] or '-'}  {f['scans']:,} scans  {f['bytes'] / 1e6:.1f} MB  "
                     f"{state}")  # fmt: skip
    return lines


#: damaged items listed per file by ``render`` (``--json`` lists every one)
_ITEMS_PER_FILE = 10


def damage_lines(doc: dict[str, Any]) -> list[str]:
    """The ``damaged:`` line and one line per damaged item (per file, at most
    ``_ITEMS_PER_FILE``) and per reader warning; ``damaged:    none`` only when every record
    of every file checked out and the reader lost nothing."""
    damaged = [f for f in doc["files"] if f.get("damage")]
    if not damaged and not doc["warnings"]:
        return ["damaged:    none"]
    items = sum(len(f["damage"]) for f in damaged)
    lines = [
        f"damaged:    {items} item(s) in {len(damaged)} file(s)"
        + (f", {doc['scans_lost']:,} scan(s) lost" if doc.get("scans_lost") else "")
    ]
    for f in damaged:
        name = Path(f["path"]).name
        lines += [f"  {name}: {text}" for text in f["damage"][:_ITEMS_PER_FILE]]
        if len(f["damage"]) > _ITEMS_PER_FILE:
            lines.append(f"  {name}: {len(f['damage']) - _ITEMS_PER_FILE} more (--json lists "
                         "every one)")  # fmt: skip
    lines += [f"  {w}" for w in doc["warnings"]]
    return lines
