"""The gates on the identified parameters: the fit converged, the motion told every free
parameter apart, and each one came out believable and precise enough.

``converged``, ``condition``, ``min_singular``, ``plausible`` and ``precision``;
docs/calibration.md gives the limits.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from loopcal.calibration.observability import CONDITION_OK
from loopcal.calibration.parameters import INDEX, UNITS

from .gate import Advice, Gate, advice_text

MIN_SINGULAR = 0.05  #: smallest minimum singular value of the scaled Jacobian
#: largest believable change per parameter group (a refitted LVDT moves its offset by mm)
CHANGE_LIMITS = {"offset": 15.0, "geometry": 3.0, "gain": 0.05}
#: largest standard deviation of an identified parameter, by unit
PRECISION = {"mm": 0.25, "mm/V": 0.01}
#: a change within this many of its standard deviations of none is not told apart from none:
#: the ``plausible`` gate puts it down to too little motion, not to the mechanism
PLAUSIBLE_SIGMA = 3.0


def _group(name: str) -> str:
    if name.startswith("d0"):
        return "offset"
    if name.startswith("S"):
        return "gain"
    return "geometry"


def converged_gate(converged: bool, message: str) -> Gate:
    """The identification converged.

    Parameters
    ----------
    converged : bool
        Whether the Levenberg-Marquardt identification converged.
    message : str
        The solver's own message (the gate's value, and part of the reason if it failed).

    Returns
    -------
    Gate
        ``"converged"``, passed exactly when ``converged``.

    Notes
    -----
    It fails for an unobservable free set or a divergence (docs/calibration.md); the
    worker makes a failed ``converged`` gate of its own when the identification raised.
    """
    if converged:
        return Gate("converged", True, message, "converged")
    return Gate(
        "converged",
        False,
        message,
        "converged",
        f"the identification did not converge ({message})",
        "record again with more, well spread still positions; check the start "
        "values in the controller config",
    )


def condition_gate(condition: float, advice: Advice) -> Gate:
    """The poses see every combination of the free parameters: a condition number <= 1000.

    Parameters
    ----------
    condition : float
        Condition number ``s_1 / s_L`` of the identification's scaled Jacobian (columns
        scaled to RMS one per pose, docs/model.md sections 6 and 7), dimensionless;
        ``inf`` when ``s_L`` is 0.
    advice : Advice
        What to do if it fails: the text, or a function making it (called only then;
        :class:`~loopcal.daemon.worker.coverage.LazyAdvice`).

    Returns
    -------
    Gate
        ``"condition"``, passed when ``condition <= CONDITION_OK``.

    Notes
    -----
    The limit, :data:`loopcal.calibration.observability.CONDITION_OK` = 1000, is the
    source paper's acceptable condition number (docs/model.md section 11: the seven
    parameters reach below it, about 15 to 70 in simulation). It fails for poses bunched in
    one part of the workspace.
    """
    return Gate.judged("condition", condition <= CONDITION_OK, condition, f"<= {CONDITION_OK:g}",
                       "some combination of parameters is barely seen by these poses",
                       advice)  # fmt: skip


def min_singular_gate(s_min: float, advice: Advice) -> Gate:
    """The poses tell every free parameter apart: a minimum singular value >= 0.05.

    Parameters
    ----------
    s_min : float
        Smallest singular value ``s_L`` of the identification's scaled Jacobian
        (docs/model.md section 7), dimensionless.
    advice : Advice
        What to do if it fails: the text, or a function making it (called only then).

    Returns
    -------
    Gate
        ``"min_singular"``, passed when ``s_min >= MIN_SINGULAR``.

    Notes
    -----
    With the Jacobian's columns scaled by ``sqrt(M) / ||g_j||`` (M poses), a scaled
    parameter's standard deviation is the residual noise over ``s``, whatever M is, so
    the limit :data:`MIN_SINGULAR` (0.05, docs/calibration.md) compares across pose sets
    of any size. The paper judges a pose set by this value together with the condition
    number.
    """
    return Gate.judged("min_singular", s_min >= MIN_SINGULAR, s_min, f">= {MIN_SINGULAR:g}",
                       "the poses hardly tell some parameters apart", advice)  # fmt: skip


def plausible_gate(
    free: list[str], previous: np.ndarray, new: np.ndarray, *, std: np.ndarray | None = None,
    imprecise: Callable[[str], str] | None = None,
) -> Gate:  # fmt: skip
    """No parameter moved further than a refit, or a blueprint tolerance, can explain.

    Parameters
    ----------
    free : list of str
        The identified parameters' names (:data:`loopcal.calibration.parameters.NAMES`).
    previous : ndarray of float, shape (20,)
        The parameters before (the controller config's), mm and mm/V.
    new : ndarray of float, shape (20,)
        The identified parameters, likewise.
    std : ndarray of float, shape (len(free),), optional
        The identified parameters' standard deviations, in the order of ``free``.
    imprecise : callable, optional
        The advice when the change at fault is within :data:`PLAUSIBLE_SIGMA` of its
        ``std`` of none, called with why (e.g. ``"A1x is known only to +-21.546 mm"``):
        the motion did not pin that parameter down
        (:func:`~loopcal.daemon.worker.gates.samples.too_little_motion`).

    Returns
    -------
    Gate
        ``"plausible"``, its value the change of the parameter closest to its limit
        (name, change and unit; ``"no change"`` when none changed), passed when every
        change is within its limit. A failure names the sensor or the geometry, unless
        the change is within its own uncertainty and ``imprecise`` says what to do.

    Notes
    -----
    :data:`CHANGE_LIMITS` (docs/calibration.md): an offset ``d0i`` may move 15 mm (a
    refitted LVDT moves its offset by millimetres), a geometry parameter (``A..``,
    ``k1``..``k3``) 3 mm (a blueprint tolerance), a gain ``Si`` 5 % of its previous value.
    It fails for the wrong sensor, a broken cable, or a config for another robot.
    """
    worst, worst_ratio = "", 0.0
    for name in free:
        i = INDEX[name]
        limit = CHANGE_LIMITS[_group(name)]
        if _group(name) == "gain":
            limit *= previous[i]
        ratio = abs(new[i] - previous[i]) / limit
        if ratio > worst_ratio:
            worst, worst_ratio = name, ratio
    if worst_ratio <= 1.0:
        if not worst:
            return Gate("plausible", True, "no change", "changes within " + _limits_text())
        i = INDEX[worst]
        change = f"largest {worst} {new[i] - previous[i]:+.3f} {UNITS[worst]}"
        return Gate("plausible", True, change, "changes within " + _limits_text())
    i = INDEX[worst]
    change = new[i] - previous[i]
    sensor = worst[-1] if worst.startswith(("d0", "S")) else None
    value, limit = f"{worst} {change:+.3f} {UNITS[worst]}", "changes within " + _limits_text()
    reason = (f"{worst} would change by {change:+.3f} {UNITS[worst]}, more than a "
              f"{'refitted LVDT' if sensor else 'blueprint tolerance'} explains")  # fmt: skip
    s = None if std is None else float(std[free.index(worst)])
    if imprecise is not None and s is not None and not abs(change) > PLAUSIBLE_SIGMA * s:
        known = f"{worst} is known only to +-{s:.3f} {UNITS[worst]}"
        return Gate("plausible", False, value, limit,
                    f"{reason}; but {known} (1 sigma): the change is not told apart from none",
                    imprecise(known))  # fmt: skip
    return Gate(
        "plausible",
        False,
        value,
        limit,
        reason,
        (
            f"check that sensor {sensor} is the one replaced, its gain S{sensor} and its wiring"
            if sensor
            else "check the controller config's geometry against the mechanism"
        ),
    )


def _limits_text() -> str:
    return (
        f"{CHANGE_LIMITS['offset']:g} mm (offsets), {CHANGE_LIMITS['geometry']:g} mm "
        f"(geometry), {100 * CHANGE_LIMITS['gain']:g} % (gains)"
    )


def precision_gate(
    free: list[str], std: np.ndarray, advice: Advice, *, seconds: float | None = None,
    limit_mm: float | None = None,
) -> Gate:  # fmt: skip
    """Every identified parameter is known well enough: std <= 0.25 mm (0.01 mm/V).

    Parameters
    ----------
    free : list of str
        The identified parameters' names, at least one.
    std : ndarray of float, shape (len(free),)
        Their standard deviations, in the order of ``free`` (mm, mm/V for the gains).
    advice : Advice
        What to do if it fails: the text, or a function making it (called only then).
    seconds : float, optional
        For a fit on every scan: the seconds of usable motion it had. The advice then says
        for how long to go on: the variance falls as one over the time for motion like
        the recorded, so about ``seconds * ((std / limit)^2 - 1)`` more.
    limit_mm : float, optional
        Another limit on lengths, mm (the daemon's upkeep asks 0.05 mm of an offset).

    Returns
    -------
    Gate
        ``"precision"``, its value the standard deviation of the parameter closest to
        its limit (name, value and unit), passed when that is within it.

    Raises
    ------
    ValueError
        If ``free`` is empty (nothing to judge).

    Notes
    -----
    :data:`PRECISION` (docs/calibration.md): 0.25 mm for lengths, 0.01 mm/V for gains.
    About one simulated 2-minute session in 20 fails it, and is told to record more.
    """
    limits = {**PRECISION, "mm": PRECISION["mm"] if limit_mm is None else limit_mm}
    ratios = [std[j] / limits[UNITS[n]] for j, n in enumerate(free)]
    j = int(np.argmax(ratios))
    name = free[j]
    return Gate.judged(
        "precision", ratios[j] <= 1.0, f"{name} {std[j]:.3f} {UNITS[name]}",
        f"<= {limits['mm']:g} mm, {limits['mm/V']:g} mm/V",
        f"{name} is known only to +-{std[j]:.3f} {UNITS[name]} (1 sigma)",
        lambda: advice_text(advice) + _for_how_long(seconds, ratios[j]),
    )  # fmt: skip


def _for_how_long(seconds: float | None, ratio: float) -> str:
    """``precision_gate``'s "for how long" (ratio: the worst std over its limit, > 1)."""
    if seconds is None or not (np.isfinite(ratio) and seconds > 0):
        return ""
    more = seconds * (ratio**2 - 1.0)
    if more > 3600:
        return "; at this pace it would take over an hour more: move the plate further"
    return f", for about {max(5, 5 * math.ceil(more / 5)):.0f} s more of such motion"
