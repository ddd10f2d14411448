"""What changed since a sensor moved: the offsets alone, refitted from the robot's own motion.

When loop closure shows that an offset moved (a sensor swapped, a loose core), the daemon's
upkeep (:mod:`loopcal.daemon.live.upkeep`) identifies only what changed, every other
parameter held at the controller config, from every usable scan since the change, whatever
moved the plate (a task loop, a hand, nothing):

1. **screen**: the four offsets fitted together (maximum likelihood on every scan, the
   channel skew corrected: :func:`~loopcal.daemon.worker.scan_poses.scans_for_fit`). An offset
   has changed when its shift from the config is at least ``threshold_mm`` and at least
   :data:`SCREEN_Z` standard deviations, counting the config's own uncertainty (its
   ``[provenance]`` std, else :data:`DEFAULT_CONFIG_STD_MM`). Where the motion cannot tell
   the four apart (a plate held still), the sensors health named are taken instead;
2. **fit**: those offsets alone, refitted by the worker (:func:`run_worker`) with the gates
   that apply to it: converged, condition, min_singular, noise, averaging, gains, holdout,
   plausible, and precision at ``target_mm`` (no spread of positions is needed to fix an
   offset the rest of the geometry pins).

Pure computation on scan rows (no I/O): the daemon runs it in a thread of low priority,
``loopcal check`` on archives.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from loopcal.calibration.errors import CalibrationError
from loopcal.calibration.parameters import INDEX, PRESETS, ParameterModel
from loopcal.calibration.pipeline import calibrate_scans

from ..config.controller import ControllerConfig
from .gates import Gate
from .job import WorkerResult, run_worker
from .scan_poses import scans_for_fit

OFFSETS = ("d01", "d02", "d03", "d04")
#: standard deviations a shift must reach to count as a change (the config's counted)
SCREEN_Z = 5.0
#: the offsets' standard deviation assumed for a config that records none, mm
DEFAULT_CONFIG_STD_MM = 0.05
#: the fewest usable scans a screen is tried on
MIN_SCANS = 100
#: an offset whose std this many times over reaches the threshold is not vouched for
UNSURE_SIGMAS = 3.0


def config_std(controller: ControllerConfig) -> dict[str, float]:
    """Each offset's standard deviation as the config's ``[provenance]`` records it (a
    loopcal calibration; a positive number), else :data:`DEFAULT_CONFIG_STD_MM`, mm."""
    std = (controller.provenance or {}).get("std") or {}
    out = {}
    for name in OFFSETS:
        s = std.get(name) if isinstance(std, dict) else None
        ok = isinstance(s, (int, float)) and not isinstance(s, bool) and np.isfinite(s) and s > 0
        out[name] = float(s) if ok else DEFAULT_CONFIG_STD_MM
    return out


def calibrated(config: ControllerConfig) -> bool:
    """Whether loopcal calibrated ``config``: its ``[provenance]`` records the fit's std."""
    std = (config.provenance or {}).get("std")
    return isinstance(std, dict) and bool(std)


def config_cov(controller: ControllerConfig) -> np.ndarray:
    """The four offsets' covariance in the config, (4, 4) mm^2: the ``offset_cov`` the
    upkeep records with its fixes (:func:`fixed_cov`), else the squares of
    :func:`config_std` on the diagonal (a person's calibration, or none)."""
    raw = (controller.provenance or {}).get("offset_cov")
    try:
        cov = np.array(raw, dtype=float)
    except (TypeError, ValueError):
        cov = np.zeros(0)
    if cov.shape == (4, 4) and np.isfinite(cov).all() and np.allclose(cov, cov.T, atol=1e-12):
        if np.linalg.eigvalsh(cov).min() > 0:
            return (cov + cov.T) / 2
    std = config_std(controller)
    return np.diag([std[n] ** 2 for n in OFFSETS])


def offset_std(controller: ControllerConfig) -> dict[str, float]:
    """Each offset's standard deviation from :func:`config_cov` (a fix's carried errors
    counted), mm."""
    var = np.diag(config_cov(controller))
    return {n: float(np.sqrt(v)) for n, v in zip(OFFSETS, var, strict=True)}


def unsure_offsets(controller: ControllerConfig, threshold_mm: float) -> tuple:
    """The offsets a config loopcal calibrated knows too poorly to vouch for
    ``threshold_mm`` (:data:`UNSURE_SIGMAS` of their std, from :func:`config_cov`, reach
    it), with their std: ``(("d02", 0.052), ...)``, mm; empty for one never calibrated
    (nothing to vouch for: health says it needs calibrating when its loops do not close)."""
    if not calibrated(controller):
        return ()
    std = offset_std(controller)
    return tuple((n, round(s, 4)) for n, s in std.items() if UNSURE_SIGMAS * s >= threshold_mm)


def fixed_cov(
    cov: np.ndarray, N: np.ndarray, names: list[str], std: dict[str, float]
) -> np.ndarray:
    """The four offsets' covariance after a fix of ``names`` alone, the others held at the
    config: each fixed one takes in what the held ones are off by, as far as their
    patterns correlate over the motion (``e_K = -N_KK^-1 N_KO e_O`` + the scans' noise).
    A robot whose motion never tells all four apart sees this grow fix after fix, though
    its loops close.

    Parameters
    ----------
    cov : ndarray, shape (4, 4)
        The offsets' covariance before, mm^2 (:func:`config_cov`).
    N : ndarray, shape (4, 4)
        Loop closure's normal equations in the four offsets over the fix's motion, 1/mm^2.
    names : list of str
        The offsets fixed.
    std : dict
        Each fixed offset's standard deviation from the scans, mm.

    Returns
    -------
    ndarray, shape (4, 4)
        mm^2.
    """
    K = [OFFSETS.index(n) for n in names]
    O = [i for i in range(4) if i not in K]
    A = np.eye(4)
    A[np.ix_(K, K)] = 0.0
    if O:
        A[np.ix_(K, O)] = -np.linalg.pinv(N[np.ix_(K, K)]) @ N[np.ix_(K, O)]
    out = A @ cov @ A.T
    out[K, K] += [std[n] ** 2 for n in names]
    return (out + out.T) / 2


@dataclass
class OffsetFit:
    """What an upkeep fit found.

    Attributes
    ----------
    changed : list of str
        The offsets found changed (``"d03"``...), in order; empty when none.
    screen : dict
        Per offset of the four-offset screen: ``shift_mm`` (fit minus config), ``std_mm``
        (the fit's), ``z`` (the shift over the fit's and the config's std together); empty
        when the motion could not tell the four apart (``screen_note`` says why).
    screen_note : str
        Why the screen named no offset, or took health's instead ("" otherwise).
    result : WorkerResult or None
        The refit of the changed offsets alone with its gates (None when none changed).
    scans : int
        Scans given (the usable ones are the result's).
    """

    changed: list[str]
    screen: dict[str, dict[str, float]] = field(default_factory=dict)
    screen_note: str = ""
    result: WorkerResult | None = None
    scans: int = 0

    @property
    def accepted(self) -> bool:
        """A change was found and its refit passed every gate."""
        return self.result is not None and self.result.accepted

    @property
    def gates(self) -> list[Gate]:
        return [] if self.result is None else self.result.gates

    def values(self) -> dict[str, float]:
        """The refitted offsets, mm."""
        r = self.result
        return {} if r is None else {n: float(r.params[INDEX[n]]) for n in self.changed}

    def std(self) -> dict[str, float]:
        """Their standard deviations, mm."""
        r = self.result
        return {} if r is None else {n: float(r.std[n]) for n in self.changed}

    def refusal(self) -> str:
        """Why it is not accepted, in words: the failed gates' reasons and advice."""
        if self.result is None:
            return self.screen_note or "no offset changed"
        return "; ".join(f"{g.name}: {g.reason}" + (f" ({g.advice})" if g.advice else "")
                         for g in self.result.failed)  # fmt: skip

    def as_json(self) -> dict[str, Any]:
        return {"changed": self.changed, "screen": self.screen, "screen_note": self.screen_note,
                "values": self.values(), "std": self.std(), "scans": self.scans,
                "accepted": self.accepted,
                "gates": [g.as_dict() for g in self.gates]}  # fmt: skip


def screen_offsets(
    scans: np.ndarray, controller: ControllerConfig, *, threshold_mm: float
) -> tuple[list[str], dict[str, dict[str, float]], str]:
    """The offsets that changed, by the four-offset screen (module docstring).

    Parameters
    ----------
    scans : ndarray of SCAN_DTYPE rows
        The scans since the change, oldest first.
    controller : ControllerConfig
        The config in force (every parameter but the offsets held at it).
    threshold_mm : float
        The smallest shift that counts, mm.

    Returns
    -------
    changed : list of str
        The offsets that moved, in order (empty: none, or the screen could not tell).
    screen : dict
        Per offset ``shift_mm``, ``std_mm``, ``z`` (empty if the fit failed).
    note : str
        Why there is no screen ("" if there is one).
    """
    usable = scans_for_fit(scans)
    if len(usable) < MIN_SCANS:
        return [], {}, f"only {len(usable)} usable scans since the change (need {MIN_SCANS})"
    start = np.array(controller.params, dtype=float)
    try:
        ident = calibrate_scans(usable.volts, PRESETS["offsets"], start).identification
    except CalibrationError as exc:
        return [], {}, f"the motion does not tell the four offsets apart ({exc})"
    cfg = config_std(controller)
    screen, changed = {}, []
    for j, name in enumerate(OFFSETS):
        shift = float(ident.params[INDEX[name]] - start[INDEX[name]])
        std = float(ident.std[j])
        z = shift / float(np.hypot(std, cfg[name]))
        screen[name] = {"shift_mm": round(shift, 5), "std_mm": round(std, 5), "z": round(z, 2)}
        if abs(shift) >= threshold_mm and abs(z) >= SCREEN_Z:
            changed.append(name)
    return changed, screen, ""


def fit_changed_offsets(
    scans: np.ndarray,
    controller: ControllerConfig,
    *,
    threshold_mm: float,
    target_mm: float,
    hint: tuple[str, ...] = (),
) -> OffsetFit:
    """Which offsets changed since the scans began, and their new values with the gates
    that apply (module docstring).

    Parameters
    ----------
    scans : ndarray of SCAN_DTYPE rows
        Every scan since the change, oldest first (moving or still).
    controller : ControllerConfig
        The config in force.
    threshold_mm : float
        The smallest shift that counts as a change, mm.
    target_mm : float
        The precision each refitted offset must reach, mm (the ``precision`` gate).
    hint : tuple of str
        Offsets health named (``"d03"``): taken when the screen cannot tell the four apart.

    Returns
    -------
    OffsetFit
    """
    changed, screen, note = screen_offsets(scans, controller, threshold_mm=threshold_mm)
    if not screen and hint:
        changed, note = list(hint), f"{note}; refitting {', '.join(hint)}, as health named"
    if not changed:
        return OffsetFit(changed, screen, note, None, len(scans))
    out = refit_offsets(scans, controller, changed, target_mm=target_mm)
    out.screen, out.screen_note = screen, note
    return out


def refit_offsets(
    scans: np.ndarray, controller: ControllerConfig, names: list[str], *, target_mm: float
) -> OffsetFit:
    """The offsets ``names`` alone refitted on ``scans``, every other parameter held at
    ``controller``, with the gates that apply (module docstring, step 2).

    Parameters
    ----------
    scans : ndarray of SCAN_DTYPE rows
        The scans to fit, oldest first (moving or still).
    controller : ControllerConfig
        The config in force.
    names : list of str
        The offsets to refit (``"d03"``...).
    target_mm : float
        The precision each must reach, mm (the ``precision`` gate).

    Returns
    -------
    OffsetFit
        ``changed`` = ``names``, no screen.
    """
    model = ParameterModel.parse(",".join(names), ())
    out = OffsetFit(list(names), scans=len(scans))
    out.result = run_worker(scans, controller, model, positions=False, precision_mm=target_mm)
    return out
