"""The calibration worker: from recordings to parameters it can vouch for.

MCAP -> poses -> fit -> gates: given the scans of the recordings (as
:func:`loopcal.daemon.recording.read_recordings` returns them), the worker takes their still poses
(:func:`loopcal.daemon.worker.recorded_poses.poses_of_scans`), keeps every fifth out of the fit to
check it
against, selects the best of the others and identifies the free parameters from them
(:func:`loopcal.calibration.pipeline.calibrate`, started from the controller config), and runs the
acceptance gates that apply to the fit (:data:`loopcal.daemon.worker.gates.GATES`). Writing the
result into the controller config is :mod:`loopcal.daemon.worker.writeback`'s job, and only
done when every gate passed.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from loopcal.calibration.errors import CalibrationError
from loopcal.calibration.identify import DEFAULT_METHOD
from loopcal.calibration.parameters import INDEX, NAMES, UNITS, ParameterModel
from loopcal.calibration.pipeline import (
    DEFAULT_N_SELECT,
    Calibration,
    calibrate,
    calibrate_scans,
)

from ..config.controller import ControllerConfig
from ..recording import RecordingFile
from ..times import now_text, time_or
from ..version import loopcal_version
from .coverage import LazyAdvice, lazy_coverage_advice
from .gates import Gate, GateContext, measure_gates
from .gates.residual import HOLDOUT_EVERY
from .recorded_poses import RecordedPoses, poses_of_scans
from .scan_poses import scans_for_fit

#: what a fit takes its samples from: every usable scan, or still poses (averaged, selected)
SAMPLES = ("scans", "poses")
METHOD_NAMES = {"ml": "maximum likelihood", "paper": "the paper's closed-loop residuals"}


@dataclass
class WorkerResult:
    """What the worker found.

    model: the free set identified. previous: (20,) the controller config's values.
    params: (20,) the new values (= previous if the identification failed).
    std: {name: standard deviation} of the free parameters. gates: the acceptance gates in
    order. poses, fit, held_out: the poses found (for a fit on every scan: the usable scans,
    :class:`~loopcal.daemon.worker.scan_poses.RecordedScans`), and indices of those fitted and
    held out (every scan is in the final fit on scans: the held-out ones were left out of a
    first fit, which the holdout gate checks). calibration: the selection and
    identification, or None if it could not run.
    n_scans: the scans it started from. span_ns: their first and last stamps (ns since the
    Unix epoch), or None. files: the recording files they came from, as read.
    advice: where the plate should go next, from the poses' coverage at the parameters the
    gates judged (:class:`~loopcal.daemon.worker.coverage.LazyAdvice`: made only if a gate
    failed and asked for it, or when the live guidance asks).
    """

    model: ParameterModel
    previous: np.ndarray
    params: np.ndarray
    std: dict[str, float]
    gates: list[Gate]
    poses: RecordedPoses
    fit: np.ndarray
    held_out: np.ndarray
    calibration: Calibration | None
    n_scans: int = 0
    span_ns: tuple[int, int] | None = None
    files: list[RecordingFile] = field(default_factory=list)
    seconds: float = 0.0
    expected_noise_volts: float = float("nan")
    extra: dict[str, Any] = field(default_factory=dict)
    method: str = DEFAULT_METHOD
    advice: LazyAdvice | None = None

    @property
    def accepted(self) -> bool:
        return all(g.passed for g in self.gates)

    @property
    def failed(self) -> list[Gate]:
        return [g for g in self.gates if not g.passed]

    def changed(self) -> list[str]:
        """Names of the parameters the result changes (free ones and those tied to them)."""
        return [n for n in NAMES if self.params[INDEX[n]] != self.previous[INDEX[n]]]

    # ------------------------------------------------------------------ output

    @staticmethod
    def _ml(ident) -> bool:
        return ident is not None and ident.method == "ml"

    @staticmethod
    def _paper(ident) -> bool:
        return ident is not None and ident.method == "paper"

    def table(self) -> str:
        """The change, parameter by parameter, with uncertainties."""
        lines = [f"{'param':>6} {'unit':>5} {'previous':>10} {'new':>10} {'change':>9} {'std':>7}"]
        for name in self.model.free:
            i = INDEX[name]
            lines.append(
                f"{name:>6} {UNITS[name]:>5} {self.previous[i]:10.4f} {self.params[i]:10.4f} "
                f"{self.params[i] - self.previous[i]:+9.4f} {self.std.get(name, float('nan')):7.4f}"
            )
        tied = [n for n in self.changed() if n not in self.model.free]
        for name in tied:
            i = INDEX[name]
            lines.append(
                f"{name:>6} {UNITS[name]:>5} {self.previous[i]:10.4f} {self.params[i]:10.4f} "
                f"{self.params[i] - self.previous[i]:+9.4f}    (tied)"
            )
        return "\n".join(lines)

    def as_json(self) -> dict[str, Any]:
        """The ``--json`` document (docs/calibration.md describes every key)."""
        cal = self.calibration
        ident = cal.identification if cal is not None else None
        out: dict[str, Any] = {
            "accepted": self.accepted,
            "method": self.method,
            "parameters": {
                n: {
                    "value": float(self.params[INDEX[n]]),
                    "std": self.std.get(n),
                    "previous": float(self.previous[INDEX[n]]),
                    "unit": UNITS[n],
                }
                for n in self.model.free
            },
            "tied": {
                n: float(self.params[INDEX[n]]) for n in self.changed() if n not in self.model.free
            },
            "indices": ident.indices.as_dict() if ident is not None else None,
            "gates": [g.as_dict() for g in self.gates],
            "poses": {
                "found": len(self.poses),
                "fit_candidates": int(len(self.fit)),
                "selected": int(len(cal.indices)) if cal is not None else 0,
                "held_out": int(len(self.held_out)),
                "scans": self.n_scans,
                "dropped_scans": self.poses.dropped,
            },
            "residual": {
                "rms_mm2": ident.rms_residual if self._paper(ident) else None,
                "rms_volts": ident.rms_residual if self._ml(ident) else None,
                "noise_volts": ident.sigma_volts if ident is not None else None,
                "expected_noise_volts": self.expected_noise_volts,
            },
            "recordings": [str(f.path) for f in self.files],
            "seconds": round(self.seconds, 3),
        }
        out.update(self.extra)
        return out

    def provenance(self, *, since: int | None, until: int | None) -> dict[str, Any]:
        """The ``[provenance]`` table written with the new values."""
        cal = self.calibration
        assert cal is not None
        ident = cal.identification
        first, last = self.span_ns if self.span_ns is not None else (None, None)

        return {
            "written_utc": now_text(),
            "loopcal": loopcal_version(),
            "recordings": [f.path.name for f in self.files],
            "recorded_from_utc": time_or(since if since is not None else first, ""),
            "recorded_until_utc": time_or(until if until is not None else last, ""),
            "poses_found": len(self.poses),
            "poses_used": int(ident.used.sum()),
            "method": ident.method,
            f"residual_rms_{'volts' if ident.method == 'ml' else 'mm2'}": round(
                float(ident.rms_residual), 6
            ),
            "noise_volts": round(float(ident.sigma_volts), 6),
            "identified": list(self.model.free),
            "std": {n: round(float(v), 6) for n, v in self.std.items()},
            "previous": {n: float(self.previous[INDEX[n]]) for n in self.changed()},
        }


def run_worker(
    scans: np.ndarray,
    controller: ControllerConfig,
    model: ParameterModel,
    *,
    files: Sequence[RecordingFile] = (),
    n_select: int = DEFAULT_N_SELECT,
    method: str = DEFAULT_METHOD,
    samples: str | None = None,
    positions: bool = True,
    precision_mm: float | None = None,
    progress: Callable[[str], None] = lambda _: None,
) -> WorkerResult:
    """Poses, fit and gates for scans of a recording (SCAN_DTYPE rows, oldest first: one
    or many files, already loaded; ``files``, what they came from, for the provenance and
    the report).

    method: the estimator (:func:`loopcal.calibration.identify.identify`). samples: what it
    fits, ``"scans"`` (every usable scan, moving or still, each a pose of its own:
    :mod:`loopcal.daemon.worker.scan_poses`; ml only, its default) or ``"poses"`` (still poses,
    averaged, of which ``n_select`` are selected: the paper's method, and ml on request).
    positions: the ``poses`` gate applies (False: an offset refitted with everything else
    held needs no spread of positions, the daemon's upkeep; the fit's own gates judge).
    precision_mm: the ``precision`` gate's limit on lengths, mm (None: its own, 0.25)."""
    t0 = time.perf_counter()
    samples = samples or ("scans" if method == "ml" else "poses")
    if samples not in SAMPLES or (samples == "scans" and method != "ml"):
        raise ValueError(f"samples={samples!r} with method={method!r}")
    per_scan = samples == "scans"
    start = np.array(controller.params, dtype=float)
    span = (int(scans["stamp_ns"][0]), int(scans["stamp_ns"][-1])) if len(scans) else None
    if per_scan:
        poses: RecordedPoses = scans_for_fit(scans)
        thinned = f", every {poses.stride}th taken" if poses.stride > 1 else ""
        progress(f"{len(scans):,} scans: {poses.usable:,} usable ({poses.seconds:.0f} s)"
                 f"{thinned}")  # fmt: skip
        held = poses.block % HOLDOUT_EVERY == HOLDOUT_EVERY // 2
    else:
        poses = poses_of_scans(scans)
        progress(
            f"{len(scans):,} scans: {len(poses)} still poses "
            f"(median {int(np.median(poses.counts)) if len(poses) else 0} scans each)"
        )
        held = np.arange(len(poses)) % HOLDOUT_EVERY == HOLDOUT_EVERY // 2
    k = np.arange(len(poses))
    fit, held_out = k[~held], k[held]
    result = WorkerResult(model, start, start.copy(), {}, [], poses, fit, held_out, None,
                          len(scans), span, list(files))  # fmt: skip
    result.method = method
    still = not per_scan
    advice = lazy_coverage_advice(poses.volts, start, still=still)  # made only if a gate fails
    result.advice = advice
    ctx = GateContext(poses, per_scan, model, start, advice, positions=positions,
                      precision_mm=precision_mm)  # fmt: skip
    result.gates += measure_gates(ctx, before_fit=True)
    if not result.accepted:
        result.seconds = time.perf_counter() - t0
        return result
    n_free = len(model.free)
    if per_scan:
        progress(f"identifying {n_free} parameters from {len(fit):,} scans, one plate rotation "
                 f"each ({METHOD_NAMES[method]}); {len(held_out):,} held out")  # fmt: skip
    else:
        progress(
            f"selecting up to {n_select} of {len(fit)} poses, identifying {n_free} parameters "
            f"({METHOD_NAMES[method]})"
        )
    try:
        if per_scan:
            # the held-out stretches check a fit that did not see them; the values written
            # then come from every usable scan (a fifth more information), started there
            checked = calibrate_scans(poses.volts[fit], model, start).identification
            progress(f"identifying again from all {len(k):,} scans, the held-out ones too")
            cal = calibrate_scans(poses.volts, model, checked.params)
            cal = replace(cal, identification=replace(cal.identification, start=start))
            fit = result.fit = k
        else:
            cal = calibrate(
                poses.volts[fit], model, start, n_select=n_select, method=method,
                scans_per_pose=poses.counts[fit],
            )  # fmt: skip
    except CalibrationError as exc:
        result.gates += measure_gates(replace(ctx, error=exc), before_fit=False)
        result.seconds = time.perf_counter() - t0
        return result
    ident = cal.identification
    result.calibration = cal
    result.params = ident.params.copy()
    result.std = {n: float(s) for n, s in zip(model.free, ident.std, strict=True)}
    advice = result.advice = lazy_coverage_advice(poses.volts, ident.params, still=still)
    if not per_scan:
        checked = ident
    ctx = replace(ctx, fit=ident, checked=checked, chosen=fit[cal.indices], held_out=held_out,
                  advice=advice)  # fmt: skip
    result.expected_noise_volts = ctx.expected_noise
    result.gates += measure_gates(ctx, before_fit=False)
    z = ctx.holdout_z
    result.extra["holdout_rms_sigma"] = float(np.sqrt(np.mean(z**2))) if len(z) else None
    result.extra["samples"] = samples
    result.seconds = time.perf_counter() - t0
    return result


def describe_files(files: Sequence[RecordingFile]) -> str:
    notes = [f"{Path(f.path).name}: {f.note}" for f in files if f.note]
    return "; ".join(notes)
