"""Loop closure over archived recordings (``loopcal check``, ``loopcal fleet check``): the
daemon's health monitor (:mod:`loopcal.daemon.live.health`, the same code and false-alarm rate) fed
file by file, and what it found: which sensor moved, from when, by how much; optionally a
trace of every test, and its plot. The same scans, in the same chunks, go to the daemon's
upkeep in report mode (:mod:`.proposals`): the recalibrations it would have proposed."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from loopcal.calibration.closure import DriftTest

from ..config.controller import load_controller_config
from ..live.health import HealthMonitor
from ..recording import read_recordings
from ..scan_rows import SCAN_DTYPE
from ..times import parse_time, time_json
from .proposals import ReportedProposals, UpkeepSettings, pending_proposal

if TYPE_CHECKING:
    from matplotlib.figure import Figure


class Trace:
    """Every test the monitor ran, for the plot: the newest pose's stamp (ns), and per sensor
    the shift (mm), its standard deviation (mm) and the statistic. Kept as numpy blocks (56
    bytes a test: a month of poses is tens of MB), and only when a plot is asked for."""

    _BLOCK = 65536

    def __init__(self) -> None:
        self._stamps: list[np.ndarray] = []
        self._values: list[np.ndarray] = []  # (block, 12) float32: shift, std, statistic
        self._n = self._BLOCK  # the fill of the last block

    def add(self, stamp_ns: int, test: DriftTest) -> None:
        if self._n == self._BLOCK:
            self._stamps.append(np.zeros(self._BLOCK, dtype=np.int64))
            self._values.append(np.zeros((self._BLOCK, 12), dtype=np.float32))
            self._n = 0
        self._stamps[-1][self._n] = stamp_ns
        self._values[-1][self._n] = np.concatenate([test.shift_mm, test.std_mm, test.statistic])
        self._n += 1

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """stamps (n,) ns; shift, std, statistic (n, 4)."""
        if not self._stamps:
            return np.zeros(0, dtype=np.int64), *(np.zeros((0, 4)),) * 3
        cut = len(self._stamps) * self._BLOCK - (self._BLOCK - self._n)
        stamps = np.concatenate(self._stamps)[:cut]
        v = np.concatenate(self._values)[:cut].astype(float)
        return stamps, v[:, 0:4], v[:, 4:8], v[:, 8:12]


def check(files: list[Path], config_path: Path, false_alarm: float, *,
          trace: bool = False, upkeep: UpkeepSettings | None = None) -> dict[str, Any]:  # fmt: skip
    """Run the monitor and the upkeep over the files, one at a time.

    Parameters
    ----------
    files : list of Path
        The recordings, oldest first.
    config_path : Path
        The controller config to check against.
    false_alarm : float
        The health monitor's probability of an alarm per still pose when nothing moved.
    trace : bool, default False
        Keep every test for the plot (under ``"_trace"``, a :class:`Trace`).
    upkeep : UpkeepSettings or None
        The upkeep's settings (None: the daemon's defaults).

    Returns
    -------
    dict
        The ``--json`` document (docs/tools.md), ``"_trace"`` included (None unless
        ``trace``).
    """
    config = load_controller_config(config_path)
    pending = pending_proposal(config)
    proposals = ReportedProposals(config, upkeep or UpkeepSettings())
    kept = Trace() if trace else None
    latest = [0]  # the newest pose's stamp when the monitor last tested
    changes: list[dict[str, Any]] = []
    first_ns: list[int] = []
    opened: list[dict[str, Any]] = []  # the loops did not close from the first poses on

    def on_test(stamp_ns: int, test: DriftTest) -> None:
        latest[0] = stamp_ns
        if kept is not None:
            kept.add(stamp_ns, test)

    def emit(kind: str, level: object, message: str, **d: Any) -> None:
        now = latest[0]
        if kind == "offset_drift_unattributed":
            best = d["candidates"][0]
            changes.append({
                "sensor": None, "candidates": [c["sensor"] for c in d["candidates"]],
                "start_utc": time_json(d["since_ns"]),
                "start_offset_s": round((d["since_ns"] - first_ns[0]) / 1e9, 3),
                "detected_utc": time_json(now), "last_report_utc": time_json(now),
                "shift_mm": best["shift_mm"], "std_mm": best["std_mm"], "shape": "step",
                "statistic": d["statistic"], "end_utc": None, "message": message,
            })  # fmt: skip
            return
        if kind == "offset_drift" and changes and changes[-1]["sensor"] is None and changes[-1][
                "end_utc"] is None and d["sensor"] in changes[-1]["candidates"]:  # fmt: skip
            changes[-1].update(sensor=d["sensor"], candidates=[d["sensor"]])  # told apart now
        if kind == "offset_drift":
            if changes and changes[-1]["sensor"] == d["sensor"] and changes[-1]["end_utc"] is None:
                changes[-1].update(shift_mm=d["shift_mm"], std_mm=d["std_mm"],
                                   shape=d["shape"], last_report_utc=time_json(now))  # fmt: skip
                return
            changes.append({
                "sensor": d["sensor"], "candidates": [d["sensor"]],
                "start_utc": time_json(d["since_ns"]),
                "start_offset_s": round((d["since_ns"] - first_ns[0]) / 1e9, 3),
                "detected_utc": time_json(now), "last_report_utc": time_json(now),
                "shift_mm": d["shift_mm"], "std_mm": d["std_mm"], "shape": d["shape"],
                "statistic": d["statistic"], "end_utc": None, "message": message,
            })  # fmt: skip
        elif kind == "offset_drift_cleared" and changes:
            changes[-1]["end_utc"] = time_json(now)
        elif kind == "loops_open":
            opened.append({
                "calibrated_utc": d.get("calibrated_utc"),
                "since_utc": time_json(d["since_ns"]), "detected_utc": time_json(d["detected_ns"]),
                "poses": d["poses"], "statistic": d["statistic"],
                "largest_sensor": d["largest_sensor"], "largest_shift_mm": d["largest_shift_mm"],
                "message": message,
            })  # fmt: skip

    monitor = HealthMonitor(config, emit, false_alarm=false_alarm, on_test=on_test)
    warnings: list[str] = []
    last_ns = None
    for path in files:
        rec = read_recordings(path)
        warnings += rec.warnings
        if len(rec):
            if not first_ns:
                first_ns.append(int(rec.scans["stamp_ns"][0]))
            last_ns = int(rec.scans["stamp_ns"][-1])
            monitor.feed(rec.scans)
            proposals.feed(rec.scans)
    monitor.feed(np.zeros(0, dtype=SCAN_DTYPE), final=True)  # the pose the recordings end in
    if proposals.failed is not None:
        warnings.append(proposals.failed)
    return {
        "changes": changes,
        "loops_open": opened[0] if opened else None,
        "loops_close": not changes and not opened,
        "proposals": proposals.found(first_ns[0] if first_ns else None),
        "pending_proposal": pending,
        "poses": monitor.state.poses,
        "threshold": round(monitor.threshold, 3),
        "false_alarm": false_alarm,
        "config": {"path": str(config.path), "sha256": config.sha256},
        "start_utc": time_json(first_ns[0] if first_ns else None),
        "end_utc": time_json(last_ns),
        "recordings": [str(f) for f in files],
        "warnings": warnings,
        "_trace": kept,
    }


def sensor_words(change: dict[str, Any]) -> str:
    """A change's sensor, or its candidates while the poses could not tell: ``3 or 4``."""
    return " or ".join(str(s) for s in change.get("candidates") or [change["sensor"]])


@dataclass(frozen=True)
class Verdict:
    """What a check found, in one place: the exit status and the words the text output ends
    with and the plot is titled by.

    status: 0 the loops close and the upkeep would propose nothing, 1 otherwise. text: why,
    e.g. "the loops do not close at this config since the recordings began: calibrate".
    """

    status: int
    text: str


def verdict(doc: dict[str, Any]) -> Verdict:
    """The :class:`Verdict` of a :func:`check` document."""
    found = []
    if (o := doc["loops_open"]) is not None:
        found.append("the loops do not close at this config since the recordings began: "
                     + ("a change since its calibration" if o["calibrated_utc"] else
                        "calibrate"))  # fmt: skip
    if changes := doc["changes"]:
        sensors = ", ".join(dict.fromkeys(sensor_words(c) for c in changes))
        found.append(f"{len(changes)} change{'s' if len(changes) > 1 else ''} found (sensor"
                     f"{'s' if ',' in sensors else ''} {sensors})")  # fmt: skip
    if proposals := doc["proposals"]:
        found.append(f"upkeep would propose {len(proposals)} recalibration"
                     + ("s" if len(proposals) > 1 else ""))  # fmt: skip
    if not found:
        return Verdict(0, "the loops close: no sensor's offset moved, nothing to propose")
    return Verdict(1, "; ".join(found))


def plot(doc: dict[str, Any], path: Path) -> None:
    """Write :func:`figure` of a check to ``path``, in the format its suffix names (``.png``,
    ``.svg``, ``.pdf``: ``loopcal check --plot`` takes no other); OSError if it cannot be
    written."""
    from ..worker.report import save_figure  # sets matplotlib's Agg backend: files only

    save_figure(figure(doc), path)


def figure(doc: dict[str, Any]) -> Figure:
    """Each sensor's estimated offset shift (with one standard deviation) and statistic
    over time, the alarm threshold, and the changes found; titled by the check's
    :func:`verdict`. The time axis is UTC, its ticks and labels chosen for the span (seconds
    to months: matplotlib's AutoDateLocator and ConciseDateFormatter)."""
    import matplotlib.dates as mdates

    from ..worker.report import plt  # matplotlib with the Agg backend: files only

    stamps, shift, std, stat = doc["_trace"].arrays()
    t = stamps.astype("datetime64[ns]")  # matplotlib plots these as UTC times
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    for i in range(4):
        line = a1.plot(t, shift[:, i], lw=1, label=f"sensor {i + 1}")[0]
        a1.fill_between(t, shift[:, i] - std[:, i], shift[:, i] + std[:, i],
                        color=line.get_color(), alpha=0.15, lw=0)  # fmt: skip
        a2.plot(t, np.maximum(stat[:, i], 0.1), lw=1, color=line.get_color(),
                label=f"sensor {i + 1}")  # fmt: skip
    a2.axhline(doc["threshold"], color="black", ls="--", lw=1,
               label=f"alarm threshold ({doc['false_alarm']:g} per pose)")  # fmt: skip
    starts = [datetime.fromtimestamp(parse_time(c["start_utc"]) / 1e9, UTC)
              for c in doc["changes"]]  # fmt: skip
    if len(starts) <= 20:
        for t0 in starts:
            for ax in (a1, a2):
                ax.axvline(t0, color="tab:red", lw=0.8)
    elif starts:  # many changes: a mark each, not a wall of lines
        a2.plot(starts, np.full(len(starts), doc["threshold"]), "v", color="tab:red", ms=3,
                label="a change began")  # fmt: skip
    a1.set_ylabel("estimated offset shift, mm")
    title = f"Loop closure at {Path(doc['config']['path']).name}: {verdict(doc).text}"
    if starts:
        title += " (red: where the changes began)"
    a1.set_title(title, fontsize=10, wrap=True)
    a2.set_ylabel("statistic (chi-square, 1 dof)")
    a2.set_yscale("log")
    a2.set_ylim(bottom=0.1)
    a2.set_xlabel("UTC" if doc["start_utc"] is None else
                  f"UTC, from {doc['start_utc']} to {doc['end_utc']}")  # fmt: skip
    locator = mdates.AutoDateLocator(tz=UTC)
    a2.xaxis.set_major_locator(locator)
    a2.xaxis.set_major_formatter(mdates.ConciseDateFormatter(locator, tz=UTC))
    for ax in (a1, a2):
        ax.legend(fontsize=8, loc="upper left")
        ax.grid(alpha=0.3)
    return fig
