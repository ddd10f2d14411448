"""Live guidance for the technician: while the plate is moved by hand, what has been
collected, how well it identifies the parameters, what to do next, and when it is enough.

About once a second the guidance runs the calibration worker itself
(:func:`loopcal.daemon.worker.job.run_worker`: every usable scan, moving or still, held-out
stretches, maximum-likelihood fit, acceptance gates) on every scan recorded so far, so its
prediction is what ``loopcal calibrate`` will report on the recording. Before the scans pass
through enough distinct positions for the worker, each free parameter's standard deviation
is predicted from the information of every usable scan at the controller config and the
noise the scans show: every scan counts, so it is enough as soon as the motion so far holds
the information, whether the plate paused or not.

It is *enough* once every offset's standard deviation is at or below the target and every
acceptance gate passes; ``loopcal record --until-enough`` then stops, with the file closed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from loopcal.calibration import implicit
from loopcal.calibration.observability import ObservabilityIndices, observability_indices
from loopcal.calibration.parameters import INDEX, SL_OFFSET, UNITS, ParameterModel
from loopcal.calibration.poses import pose_noise_volts

from ..config.controller import ControllerConfig
from ..scan_rows import volts as scans_volts
from ..worker import coverage as C
from ..worker.gates.samples import MIN_POSES
from ..worker.job import run_worker
from ..worker.scan_poses import RecordedScans, scans_for_fit
from .guidance_defaults import TARGET_MM

PERIOD_S = 1.0
OFFSETS = tuple(n for n in INDEX if SL_OFFSET.start <= INDEX[n] < SL_OFFSET.stop)
#: the plate has not moved for RESTING_S seconds when every channel stayed within
#: RESTING_BAND_V over them: the technician is asked to move on
RESTING_S, RESTING_BAND_V = 10.0, 0.25
#: the coverage (largest tilt toward each sensor, largest twist) is judged on at most this
#: many scans
COVERAGE_SCANS = 2000


@dataclass
class GuidanceUpdate:
    """One update of the live guidance.

    elapsed_s: the plate's time since the first scan (scans over the scan rate); scans:
    collected so far; poses: the distinct positions the usable scans passed through
    (:func:`loopcal.daemon.worker.coverage.distinct_positions`, what the ``poses`` gate counts).
    reach_deg: (4,) the largest tilt reached toward each sensor. twist_deg: (2,) the largest
    twist about the plate's own axis, clockwise and counter-clockwise seen from above
    (:func:`loopcal.daemon.worker.coverage.twist_coverage`). min_singular, condition:
    of the worker's fit (before it can run: of every usable scan's maximum-likelihood
    information; None before they identify every parameter).
    std: {name: predicted standard deviation} of each free parameter. gates: {name:
    passed} (empty before the worker can run). enough: the target is met and every gate
    passes. instruction: what to do next. advice: the same, for a program to follow
    (:class:`~loopcal.daemon.worker.coverage.NextMove`: tilt toward which sensor, twist
    which way, how far, anywhere, enough; its ``text`` is the instruction, or its start
    when a failing gate adds to it).
    """

    elapsed_s: float
    scans: int
    poses: int
    reach_deg: list[float]
    min_singular: float | None
    condition: float | None
    std: dict[str, float]
    target_mm: float
    gates: dict[str, bool] = field(default_factory=dict)
    enough: bool = False
    instruction: str = ""
    twist_deg: list[float] = field(default_factory=lambda: [0.0, 0.0])
    advice: C.NextMove | None = None

    def as_json(self) -> dict[str, Any]:
        def num(x: float | None) -> float | None:
            return None if x is None or not np.isfinite(x) else round(float(x), 6)

        return {
            "elapsed_s": round(self.elapsed_s, 1),
            "scans": self.scans,
            "poses": self.poses,
            "reach_deg": {f"sensor{i + 1}": round(r, 1) for i, r in enumerate(self.reach_deg)},
            "twist_deg": dict(zip(("clockwise", "counter_clockwise"),
                                  (round(t, 1) for t in self.twist_deg), strict=True)),
            "min_singular": num(self.min_singular),
            "condition": num(self.condition),
            "std": {n: num(s) for n, s in self.std.items()},
            "target_mm": self.target_mm,
            "gates": self.gates,
            "enough": self.enough,
            "instruction": self.instruction,
            "advice": self.advice.as_json() if self.advice is not None else None,
        }

    def render(self) -> list[str]:
        """The lines of the terminal display."""
        m, s = divmod(int(self.elapsed_s), 60)
        lines = [
            f"loopcal guidance  {m:d}:{s:02d}  scans {self.scans:,}  positions {self.poses}"
            f" (need {MIN_POSES})",
            f"coverage, largest tilt toward each sensor (aim for {C.GOOD_TILT_DEG:.0f} deg):",
        ]
        for i, r in enumerate(self.reach_deg):
            bar = "#" * int(min(r, 45) / 45 * 30)
            lines.append(f"  sensor {i + 1} {r:5.1f} deg |{bar:<30}|")
        cw, ccw = self.twist_deg
        lines.append(f"twist about the plate's axis (aim for {C.GOOD_TWIST_DEG:.0f} deg each way): "
                     f"clockwise {cw:.1f} deg, counter-clockwise {ccw:.1f} deg")  # fmt: skip
        if self.min_singular is not None:
            lines.append(
                f"observability: min singular value {self.min_singular:.3f}, condition "
                f"{self.condition:.1f}"
            )
        lines.append(f"predicted standard deviations (target {self.target_mm:g} mm on offsets):")
        for name, sd in self.std.items():
            unit = UNITS[name]
            mark = ""
            if name in OFFSETS:
                mark = "ok" if sd <= self.target_mm else "  "
            text = f"{sd:7.3f}" if np.isfinite(sd) else "      -"
            lines.append(f"  {name:>4} {text} {unit:<4} {mark}")
        if self.gates:
            lines.append(
                "gates: " + " ".join(f"{n}{'+' if ok else '-'}" for n, ok in self.gates.items())
            )
        lines.append(("ENOUGH: " if self.enough else "next: ") + self.instruction)
        return lines


class Guidance:
    """An observer of the recorder's scans (:mod:`loopcal.daemon.recorder.observers`) that predicts
    the calibration and says what to do next.

    controller: the config in force (the calibration's start). model: the free set.
    target_mm: every offset's standard deviation must reach this. on_update: called with
    each :class:`GuidanceUpdate`; on_enough: called once when it is enough.
    """

    name = "live guidance"

    def __init__(
        self,
        controller: ControllerConfig,
        model: ParameterModel,
        *,
        target_mm: float = TARGET_MM,
        on_update: Callable[[GuidanceUpdate], None] = lambda _: None,
        on_enough: Callable[[GuidanceUpdate], None] = lambda _: None,
        period_s: float = PERIOD_S,
    ) -> None:
        if not (np.isfinite(target_mm) and target_mm > 0):
            raise ValueError(f"the target must be a positive number of mm, got {target_mm!r}")
        self.controller = controller
        self.model = model
        self.target_mm = float(target_mm)
        self.on_update = on_update
        self.on_enough = on_enough
        self.period_s = period_s
        self._chunks: list[np.ndarray] = []
        self._next = 0.0
        self.last: GuidanceUpdate | None = None
        self.done = False

    def feed(self, rows: np.ndarray) -> None:
        self._chunks.append(rows)
        now = time.monotonic()
        if now >= self._next and not self.done:
            self._next = now + self.period_s
            self.update()

    def reload(self, controller: ControllerConfig) -> None:
        """A reload put another controller config in force: predict at it from now on."""
        self.controller = controller

    def status(self) -> str:
        u = self.last
        if u is None:
            return "guidance: waiting for scans"
        worst = max((u.std[n] for n in OFFSETS if n in u.std), default=float("nan"))
        return (
            f"guidance: {u.poses} positions, offsets std {worst:.3f} mm (target "
            f"{u.target_mm:g}){', ENOUGH' if u.enough else ''}"
        )

    # ------------------------------------------------------------------ the prediction

    def update(self) -> GuidanceUpdate:
        """Assess everything recorded so far (also called by :meth:`feed`)."""
        scans = np.concatenate(self._chunks) if self._chunks else None
        if scans is None or len(scans) == 0:
            raise ValueError("no scans yet")
        self._chunks = [scans]
        start = np.array(self.controller.params, dtype=float)
        usable = scans_for_fit(scans)
        elapsed = len(scans) / usable.scan_rate_hz  # of the plate's time, whatever the clock
        step = max(1, -(-len(usable) // COVERAGE_SCANS))
        reach, twist = C.reach_and_twist(usable.volts[::step], start)
        positions = C.distinct_positions(usable.volts)
        u = GuidanceUpdate(elapsed, len(scans), positions, [float(r) for r in reach], None,
                           None, {}, self.target_mm,
                           twist_deg=[float(t) for t in twist])  # fmt: skip
        if positions >= MIN_POSES:
            self._from_worker(u, scans)
        else:
            u.std, indices = self._predicted_std(usable, start)
            if indices is not None:
                u.min_singular, u.condition = indices.min_singular, indices.condition
            self._advise(u, usable, scans, lambda: (
                C.next_move(reach, twist, start, still=False) if len(usable)
                else C.coverage_move(usable.volts, start, still=False)))  # fmt: skip
        self.last = u
        self.on_update(u)
        if u.enough and not self.done:
            self.done = True
            self.on_enough(u)
        return u

    def _from_worker(self, u: GuidanceUpdate, scans: np.ndarray) -> None:
        result = run_worker(scans, self.controller, self.model)
        u.gates = {g.name: bool(g.passed) for g in result.gates}
        u.std = {n: float(result.std.get(n, np.inf)) for n in self.model.free}
        cal = result.calibration
        if cal is not None:
            u.min_singular = cal.identification.indices.min_singular
            u.condition = cal.identification.indices.condition
        offsets_ok = all(u.std.get(n, 0.0) <= self.target_mm for n in OFFSETS if n in u.std)
        u.enough = bool(result.accepted and offsets_ok)
        if u.enough:
            u.advice = C.NextMove(
                "enough",
                "enough: the recording is complete; put the plate down "
                "(loopcal calibrate will write the new offsets)",
            )
            u.instruction = u.advice.text
            return
        failed = result.failed
        coverage = result.advice
        assert coverage is not None  # the worker's coverage advice, made once for both
        if failed and failed[0].advice:
            # a gate's advice is the coverage advice (made when it failed), or its own
            u.instruction = text = failed[0].advice
            own = not (coverage.made and text.startswith(coverage.move().text))
            u.advice = C.NextMove("other", text) if own else coverage.move()
        else:
            self._advise(u, result.poses, scans, coverage.move)

    def _predicted_std(
        self, usable: RecordedScans, p: np.ndarray
    ) -> tuple[dict[str, float], ObservabilityIndices | None]:
        """Each free parameter's standard deviation from the usable scans' ML information at
        the config (inf while they cannot identify them all), and their indices."""
        n = self.model.n_free
        out = dict.fromkeys(self.model.free, float("inf"))
        if len(usable) < n:
            return out, None
        w = 1.0 / pose_noise_volts(usable.scan_noise, usable.counts)
        R, ok = implicit.start_rotations(usable.volts, p)
        if ok.sum() < n or not np.all(np.isfinite(w[ok])):
            return out, None
        a = implicit.weighted_information(R[ok], p, self.model.tie_matrix, w[ok])
        info = a.T @ a
        if np.linalg.cond(info) > 1e12:
            return out, None
        std = np.sqrt(np.diag(np.linalg.inv(info)))
        indices = observability_indices(a[:, None, :])
        return {name: float(s) for name, s in zip(self.model.free, std, strict=True)}, indices

    def _advise(
        self,
        u: GuidanceUpdate,
        usable: RecordedScans,
        scans: np.ndarray,
        advice: Callable[[], C.NextMove],
    ) -> None:
        """What to do next, into ``u.advice`` and ``u.instruction``: move anywhere, if the
        plate has rested; else ``advice()``, the coverage advice."""
        n = round(RESTING_S * usable.scan_rate_hz)  # by scan count: stamps may be packed
        u.advice = None
        if len(scans) >= n:
            volts = scans_volts(scans[-n:])
            if np.all(np.ptp(volts, axis=0) <= RESTING_BAND_V):
                u.advice = C.NextMove("anywhere", "move the plate: tilt and twist it by hand "
                                      "through new positions")  # fmt: skip
        if u.advice is None:
            u.advice = advice()
        u.instruction = u.advice.text
