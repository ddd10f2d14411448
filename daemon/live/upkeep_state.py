"""What the upkeep knows, kept across restarts: its baseline and any change in progress.

The upkeep (:mod:`.upkeep`) tells a change by testing the loops against a baseline, and a
change takes a few segments to stand, be told apart and be fixed. A SIGKILL, a power cut
or a reboot must neither open a window in which a change goes unseen (a new baseline
taken after a swap made while the daemon was down would take the swap in) nor forget a
change in progress. Both live in one small JSON file, :data:`STATE_NAME` in the
recordings directory, which the recordings' own tools ignore:

- written durably (:func:`loopcal.daemon.config.durable.replace`: a temporary file synced,
  renamed over, the directory synced) after every segment that changed what it holds,
  and at most :data:`SAVE_EVERY_S` apart otherwise (what ``loopcal upkeep status``
  shows of a daemon that runs);
- taken up again at start only when it was made at the same *reference*: the digest of
  the 20 parameter values the loops are closed at (:func:`reference_digest`). A config a
  person calibrated starts a new baseline; the config the upkeep itself wrote, or a
  proposal a person applied, has the values the record already moved to;
- refused, naming why, when it is damaged or of another format version: the daemon then
  sets it aside (renamed ``.damaged``, nothing lost), says so, and starts over from the
  reference's own calibration.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import durable
from ..times import name_stamp
from .changes import Normal

log = logging.getLogger(__name__)

#: the file in the recordings directory
STATE_NAME = "upkeep-state.json"
#: the format's version; a newer one is refused
VERSION = 1
#: s of the scans' stamps between two saves when nothing else changed
SAVE_EVERY_S = 60.0
#: per-segment shifts kept for the trend test (10 minutes of 15-s segments)
TREND_SEGMENTS = 40


def state_path(directory: str | os.PathLike) -> Path:
    """Where the upkeep of a recordings directory keeps its record."""
    return Path(directory) / STATE_NAME


def reference_digest(params: np.ndarray) -> str:
    """The digest of a reference: SHA-256 of its 20 values as little-endian doubles."""
    raw = np.asarray(params, dtype="<f8").tobytes()
    return hashlib.sha256(raw).hexdigest()


@dataclass
class Change:
    """A change the loops show against the baseline: a candidate (one segment moved) or a
    standing one (two or more).

    Attributes
    ----------
    since_ns : int
        Since when the config in force is wrong: the start of the first segment that
        moved, ns.
    first : Normal
        The segment the change (or its latest step) fell inside of: left out of the
        attribution and the fit, which a few scans from before it would bias.
    first_end_ns : int
        Its end: the refit takes scans from here on.
    rest : Normal
        The segments after it, linearised at ``point``.
    point : ndarray, shape (4,)
        Where ``rest`` is linearised: the reference config's offsets moved by this much, mm
        (the change's best explanation when it was last linearised; zeros at first).
    names : list of str
        The offsets told apart (empty while the motion cannot tell).
    candidates : list of dict
        The explanations not ruled out, best first
        (:meth:`~loopcal.daemon.live.changes.Explanation.as_json`).
    advice : str
        While there are several, the move that would tell them apart.
    announced : bool
        Said (event ``offset_change``).
    refused : bool
        Said that the motion does not identify it (event ``recalibration_refused``).
    steps : int
        Times it moved on while it stood (a second step, or a creep): the scans since the
        latest one alone tell what the config needs now.
    gradual : bool
        Opened by a minute of segments together, no one of them telling it (a creep, or a
        shift near the threshold), not by one segment (a step).
    """

    since_ns: int
    first: Normal
    first_end_ns: int
    rest: Normal = field(default_factory=Normal)
    point: np.ndarray = field(default_factory=lambda: np.zeros(4))
    names: list[str] = field(default_factory=list)
    candidates: list[dict[str, Any]] = field(default_factory=list)
    advice: str = ""
    announced: bool = False
    refused: bool = False
    steps: int = 0
    gradual: bool = False

    @property
    def stood(self) -> bool:
        return self.rest.segments > 0

    def as_json(self) -> dict[str, Any]:
        return {
            "since_ns": self.since_ns,
            "first": self.first.as_json(),
            "first_end_ns": self.first_end_ns,
            "rest": self.rest.as_json(),
            "point": [float(x) for x in self.point],
            "names": list(self.names),
            "candidates": self.candidates,
            "advice": self.advice,
            "announced": self.announced,
            "refused": self.refused,
            "steps": self.steps,
            "gradual": self.gradual,
        }

    @classmethod
    def from_json(cls, doc: Any) -> Change:
        d = _table(
            doc,
            "change",
            {
                "since_ns",
                "first",
                "first_end_ns",
                "rest",
                "point",
                "names",
                "candidates",
                "advice",
                "announced",
                "refused",
                "steps",
                "gradual",
            },
        )
        point = d["point"]
        if not (
            isinstance(point, list)
            and len(point) == 4
            and all(type(x) in (int, float) and abs(x) < 1e3 for x in point)
        ):
            raise ValueError("change: point must be 4 shifts in mm")
        names = d["names"]
        if not isinstance(names, list) or not all(n in ("d01", "d02", "d03", "d04") for n in names):
            raise ValueError("change: names must be a list of d01..d04")
        if not isinstance(d["candidates"], list):
            raise ValueError("change: candidates must be a list of tables")
        if not isinstance(d["advice"], str):
            raise ValueError("change: advice must be a text")
        return cls(
            _ns(d, "since_ns"),
            Normal.from_json(d["first"]),
            _ns(d, "first_end_ns"),
            Normal.from_json(d["rest"]),
            np.array(point, dtype=float),
            list(names),
            [_candidate(c) for c in d["candidates"]],
            d["advice"],
            _flag(d, "announced"),
            _flag(d, "refused"),
            _count(d, "steps"),
            _flag(d, "gradual"),
        )


@dataclass
class UpkeepRecord:
    """Everything the upkeep keeps across restarts (module docstring).

    Attributes
    ----------
    reference : str
        :func:`reference_digest` of the values the loops are closed at.
    config_sha256 : str
        The controller config's file when the reference took force (for people).
    watching_since_ns : int
        When the upkeep began watching at this reference, ns (scans' stamps).
    baseline : Normal
        The unchanged segments at this reference (at most
        :data:`~loopcal.daemon.live.changes.BASELINE_SEGMENTS`).
    change : Change or None
        The change in progress.
    acted : dict
        Offset -> [the end of the window of the last proposal or write naming it, ns; the
        shift it made, mm; whether its change was gradual].
    trend : list
        The latest segments' single-sensor shifts: ``[end_ns, [4 shifts], [4 std]]``, mm.
    last_action : dict or None
        The last proposal or write: ``kind``, ``ns``, ``values``, ``shift_mm``, ``std``,
        ``path``.
    refusals : int
        Changes refused since the reference took force.
    last_refusal : dict or None
        The latest: ``ns``, ``names``, ``why``.
    tested : int
        Segments tested at this reference.
    tested_until_ns : int
        The end of the latest one, ns (0: none yet).
    uncalibrated : bool
        The loops did not close from the first segment on at a config loopcal never
        calibrated: nothing to keep up until a person calibrates.
    creeping : list of str
        The offsets said to creep toward the threshold (said once while they do).
    settle : list of str
        Those whose creep just stopped: what it left under the threshold is settled with
        the next minute of segments.
    """

    reference: str
    config_sha256: str
    watching_since_ns: int
    baseline: Normal = field(default_factory=Normal)
    change: Change | None = None
    acted: dict[str, list] = field(default_factory=dict)
    trend: list[list[Any]] = field(default_factory=list)
    last_action: dict[str, Any] | None = None
    refusals: int = 0
    last_refusal: dict[str, Any] | None = None
    tested: int = 0
    tested_until_ns: int = 0
    uncalibrated: bool = False
    creeping: list[str] = field(default_factory=list)
    settle: list[str] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        return {
            "version": VERSION,
            "reference": self.reference,
            "config_sha256": self.config_sha256,
            "watching_since_ns": self.watching_since_ns,
            "baseline": self.baseline.as_json(),
            "change": None if self.change is None else self.change.as_json(),
            "acted": dict(self.acted),
            "trend": self.trend,
            "last_action": self.last_action,
            "refusals": self.refusals,
            "last_refusal": self.last_refusal,
            "tested": self.tested,
            "tested_until_ns": self.tested_until_ns,
            "uncalibrated": self.uncalibrated,
            "creeping": list(self.creeping),
            "settle": list(self.settle),
        }

    @classmethod
    def from_json(cls, doc: Any) -> UpkeepRecord:
        """The record :meth:`as_json` wrote. Raises ValueError, naming what is wrong, for
        anything else (a newer version: naming it)."""
        if (
            isinstance(doc, dict)
            and isinstance(doc.get("version"), int)
            and (doc["version"] > VERSION)
        ):
            raise ValueError(
                f"format version {doc['version']}, newer than this loopcal's "
                f"{VERSION}: upgrade loopcal"
            )
        d = _table(
            doc,
            "record",
            {
                "version",
                "reference",
                "config_sha256",
                "watching_since_ns",
                "baseline",
                "change",
                "acted",
                "trend",
                "last_action",
                "refusals",
                "last_refusal",
                "tested",
                "tested_until_ns",
                "uncalibrated",
                "creeping",
                "settle",
            },
        )
        if d["version"] != VERSION:
            raise ValueError(f"format version {d['version']!r}, not {VERSION}")
        for key in ("reference", "config_sha256"):
            if not isinstance(d[key], str) or len(d[key]) != 64:
                raise ValueError(f"record: {key} must be a SHA-256 in hex")
        acted = d["acted"]
        if not isinstance(acted, dict) or not all(
            k in ("d01", "d02", "d03", "d04")
            and isinstance(v, list)
            and len(v) == 3
            and type(v[0]) is int
            and type(v[1]) in (int, float)
            and np.isfinite(v[1])
            and type(v[2]) is bool
            for k, v in acted.items()
        ):
            raise ValueError(
                "record: acted must map d01..d04 to [time in ns, shift in mm, gradual]"
            )
        for key in ("creeping", "settle"):
            if not isinstance(d[key], list) or not all(
                n in ("d01", "d02", "d03", "d04") for n in d[key]
            ):
                raise ValueError(f"record: {key} must be a list of d01..d04")
        for key in ("last_action", "last_refusal"):
            if d[key] is not None and not isinstance(d[key], dict):
                raise ValueError(f"record: {key} must be a table or null")
        return cls(
            d["reference"],
            d["config_sha256"],
            _ns(d, "watching_since_ns"),
            Normal.from_json(d["baseline"]),
            None if d["change"] is None else Change.from_json(d["change"]),
            {k: list(v) for k, v in acted.items()},
            _trend(d["trend"]),
            d["last_action"],
            _count(d, "refusals"),
            d["last_refusal"],
            _count(d, "tested"),
            _ns(d, "tested_until_ns"),
            _flag(d, "uncalibrated"),
            list(d["creeping"]),
            list(d["settle"]),
        )

    def trend_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The trend's segment ends (k,) ns, shifts and std (k, 4) mm, as arrays."""
        t, shift, std = (np.array(x, dtype=float) for x in zip(*self.trend, strict=True))
        return t, shift, std

    def note_trend(self, end_ns: int, shift: np.ndarray, std: np.ndarray) -> None:
        """Keep a segment's single-sensor shifts (the latest :data:`TREND_SEGMENTS`)."""
        if not (np.isfinite(shift).all() and np.isfinite(std).all()):
            return
        self.trend.append(
            [int(end_ns), [round(float(s), 6) for s in shift], [round(float(s), 6) for s in std]]
        )
        del self.trend[:-TREND_SEGMENTS]


def load_record(path: Path) -> UpkeepRecord | None:
    """The record at ``path``, or None if there is none.

    Raises
    ------
    ValueError
        The file is not a record this loopcal wrote (naming why).
    OSError
        It cannot be read.
    """
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None
    try:
        doc = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ValueError(f"not JSON ({exc})") from None
    return UpkeepRecord.from_json(doc)


def save_record(path: Path, record: UpkeepRecord) -> None:
    """Write ``record`` durably (module docstring). Raises OSError."""
    text = json.dumps(record.as_json(), separators=(",", ":"), allow_nan=False)
    durable.replace(path, text.encode("utf-8"), prefix="upkeep-")


def set_aside(path: Path) -> Path:
    """Rename a record that cannot be taken up to ``NAME.<UTC>.damaged``; returns it."""
    aside = path.with_name(f"{path.name}.{name_stamp()}.damaged")
    os.replace(path, aside)
    durable.fsync_dir(path.parent)
    return aside


class Keeper:
    """Keeps the upkeep's record at ``path`` (None: in memory only): takes it up at start,
    saves it when it changed (or :data:`SAVE_EVERY_S` went by), and says once when it
    cannot (a full disk: the upkeep goes on, and a restart then would start over).

    Parameters
    ----------
    path : Path or None
        The record's file (:func:`state_path`).
    """

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self.saved_ns = 0
        self.failed = False

    def take_up(
        self,
        digest: str,
        config_sha256: str,
        current: UpkeepRecord | None,
        damaged: Callable[[str, str], None],
    ) -> UpkeepRecord:
        """The record at reference ``digest``: ``current`` if it is at it, else (at start)
        the one kept, else a new one (the last action carried over, for the status).
        ``damaged(why, where)`` is told of a kept record that cannot be taken up, after it
        was set aside."""
        if current is not None and current.reference == digest:
            return current
        kept = None
        if self.path is not None and current is None:
            try:
                kept = load_record(self.path)
            except (ValueError, OSError) as exc:
                try:
                    where = str(set_aside(self.path))
                except OSError as err:
                    where = f"nowhere ({err.strerror or err})"
                damaged(str(exc), where)
        if kept is not None and kept.reference == digest:
            return kept
        old = current if current is not None else kept
        self.saved_ns = 0
        return UpkeepRecord(
            digest, config_sha256, 0, last_action=None if old is None else old.last_action
        )

    def save(self, record: UpkeepRecord, now_ns: int | None = None, dirty: bool = True) -> None:
        """Save ``record`` if ``dirty`` or a while went by (module docstring)."""
        if self.path is None:
            return
        if now_ns is not None and not dirty and now_ns - self.saved_ns < SAVE_EVERY_S * 1e9:
            return
        try:
            save_record(self.path, record)
        except OSError as exc:
            if not self.failed:
                log.error(
                    "upkeep: cannot keep its record in %s (%s): a restart now would "
                    "start its baseline over",
                    self.path,
                    exc.strerror or exc,
                )
            self.failed = True
            return
        if self.failed:
            log.info("upkeep: its record is kept again in %s", self.path)
        self.failed = False
        self.saved_ns = now_ns if now_ns is not None else time.time_ns()


def _table(doc: Any, what: str, keys: set[str]) -> dict[str, Any]:
    if not isinstance(doc, dict):
        raise ValueError(f"{what}: not a table")
    if set(doc) != keys:
        odd = sorted(set(doc) ^ keys)
        raise ValueError(f"{what}: keys {', '.join(map(str, odd))} missing or unknown")
    return doc


def _candidate(doc: Any) -> dict[str, Any]:
    """An explanation as :meth:`~loopcal.daemon.live.changes.Explanation.as_json` wrote it."""
    d = _table(doc, "candidate", {"names", "shift_mm", "std_mm", "statistic"})
    names, k = d["names"], len(d["names"]) if isinstance(d["names"], list) else 0
    ok = (
        0 < k <= 4
        and all(n in ("d01", "d02", "d03", "d04") for n in names)
        and all(
            isinstance(d[key], list)
            and len(d[key]) == k
            and all(type(x) in (int, float) and np.isfinite(x) for x in d[key])
            for key in ("shift_mm", "std_mm")
        )
        and type(d["statistic"]) in (int, float)
        and np.isfinite(d["statistic"])
    )
    if not ok:
        raise ValueError("candidate: names d01..d04, each with a shift_mm and a std_mm")
    return d


def _ns(d: dict[str, Any], key: str) -> int:
    v = d[key]
    if type(v) is not int or not 0 <= v < 1 << 63:
        raise ValueError(f"{key} must be a time in ns since the epoch")
    return v


def _count(d: dict[str, Any], key: str) -> int:
    v = d[key]
    if type(v) is not int or v < 0:
        raise ValueError(f"{key} must be a count")
    return v


def _flag(d: dict[str, Any], key: str) -> bool:
    if type(d[key]) is not bool:
        raise ValueError(f"{key} must be true or false")
    return d[key]


def _trend(doc: Any) -> list[list[Any]]:
    if not isinstance(doc, list) or len(doc) > TREND_SEGMENTS:
        raise ValueError(f"trend must be a list of at most {TREND_SEGMENTS} segments")
    for row in doc:
        ok = (
            isinstance(row, list)
            and len(row) == 3
            and type(row[0]) is int
            and all(isinstance(v, list) and len(v) == 4 for v in row[1:])
            and all(type(x) in (int, float) and np.isfinite(x) for v in row[1:] for x in v)
        )
        if not ok:
            raise ValueError("trend: each segment must be [end_ns, [4 shifts], [4 std]]")
    return [list(r) for r in doc]
