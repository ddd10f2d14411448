"""Select the best poses of a recording and identify the parameters from them."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .defaults import CONDITION_OK, DEFAULT_METHOD, DEFAULT_N_SELECT, METHODS
from .errors import CalibrationError, InputError
from .identify import Identification, identify
from .parameters import NOMINAL, PAPER7, ParameterModel
from .residuals import check_volts
from .selection import Selection, candidate_jacobian, ml_candidates, select_poses
from .simulate import NEAR_SINGULAR_MM

#: above this many times n_select candidates, a first estimate comes from PRESTART_POSES
PRESTART_FACTOR = 4
PRESTART_POSES = 400
#: candidates keep this many times the near-singular margin (with few, and with many)
CANDIDATE_MARGIN, CANDIDATE_MARGIN_MANY = 1.5, 3.0


@dataclass(frozen=True)
class Calibration:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    identification : Identification
        The final estimate, from the selected poses (its ``start`` is the caller's start).
    selection : Selection or None
        The chosen poses; ``selection.indices`` index the recording's poses. None for a fit
        on every pose given (:func:`calibrate_scans`).
    rounds : int
        How many select-and-identify rounds ran.
    """

    identification: Identification
    selection: Selection | None
    rounds: int

    @property
    def indices(self) -> np.ndarray:
        """The poses given to the final identification, as indices of the caller's poses."""
        if self.selection is not None:
            return self.selection.indices
        return np.arange(len(self.identification.used))


def calibrate(
    volts: np.ndarray,
    model: ParameterModel = PAPER7,
    start: np.ndarray = NOMINAL,
    *,
    n_select: int = DEFAULT_N_SELECT,
    criterion: str = "min_singular",
    max_condition: float = CONDITION_OK,
    rounds: int = 2,
    noise_volts: float | None = None,
    method: str = DEFAULT_METHOD,
    scans_per_pose: np.ndarray | None = None,
) -> Calibration:
    """Choose ``n_select`` of the recorded poses and identify the parameters from them.

    Parameters
    ----------
    volts : array_like, shape (N, 4)
        LVDT readings of the recorded quasi-static poses, V (for example
        :func:`~loopcal.calibration.poses.still_poses`).
    model : ParameterModel, default PAPER7
        Which parameters are free, tied and fixed.
    start : array_like, shape (20,), default NOMINAL
        Full parameter vector to start from (mm, mm/V).
    n_select : int
        Poses to select (at least ``model.n_free`` are).
    criterion : str, default "min_singular"
        Selection criterion, one of :data:`~loopcal.calibration.selection.CRITERIA`.
    max_condition : float, default CONDITION_OK
        Bound on the condition number of the selected set.
    rounds : int, default 2
        Select-and-identify rounds at most (at least one runs).
    noise_volts : float, optional
        Known per-channel noise of one scan, 1 sigma, V; None estimates it (see
        :func:`identify`).
    method : {"ml", "paper"}, default "ml"
        The estimator (see :func:`identify`); the poses are selected on that estimator's
        information.
    scans_per_pose : array_like, shape (N,), optional
        Scans averaged into each pose (ml weighs the poses by them, in the selection and
        the fit).

    Returns
    -------
    Calibration
        The identification from the selected poses, the selection and the rounds run.

    Raises
    ------
    InputError
        An unknown method, bad readings, ``scans_per_pose`` not one count per pose, or
        too few usable poses.
    ParameterError, UnobservableError, ConvergenceError
        From :func:`identify` on the selected poses.

    Notes
    -----
    The first round designs the selection at ``start``; each further round designs it again
    at the previous estimate, where the Jacobian (and which poses are near-singular) is
    closer to the truth, and identifies again; a round that selects the same poses as the
    one before ends the rounds. With N <= n_select every usable pose is selected. With
    more than PRESTART_FACTOR x n_select candidates, the first round designs at an estimate
    from PRESTART_POSES poses spread evenly over the recording instead of at ``start``
    (unless that estimate fails).
    """
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    V = check_volts(volts)
    p = np.asarray(start, dtype=float)
    counts = None if scans_per_pose is None else np.asarray(scans_per_pose, dtype=float)
    if counts is not None and counts.shape != (len(V),):
        raise InputError(f"scans_per_pose must hold one count per pose ({len(V)})")

    def fit(idx: np.ndarray, p: np.ndarray) -> Identification:
        return identify(
            V[idx], model, p, method=method, noise_volts=noise_volts,
            scans_per_pose=None if counts is None else counts[idx],
        )  # fmt: skip

    if len(V) > PRESTART_FACTOR * n_select:
        # Many candidates: the best set lies at the edges of the workspace, where poses turn
        # near-singular if the start is millimetres off. A first estimate from an even
        # spread of poses puts the selection's screening where the mechanism really is.
        spread = np.linspace(0, len(V) - 1, min(len(V), PRESTART_POSES)).round().astype(int)
        try:
            p = fit(spread, p).params
        except CalibrationError:
            pass  # select at the start, as for few candidates
    # With many candidates the set can afford to stay further from singular poses: the best
    # set otherwise gathers at the edge, where a small move of the estimate loses poses that
    # carry a whole direction of the information.
    margin = CANDIDATE_MARGIN_MANY if len(V) > PRESTART_FACTOR * n_select else CANDIDATE_MARGIN
    result: Identification | None = None
    previous: np.ndarray | None = None
    rounds_run = 0
    while rounds_run < max(rounds, 1):
        rounds_run += 1
        # candidates keep a wider margin from singularity than identification demands, so
        # that a chosen pose stays usable as the estimate moves
        if method == "ml":
            cand = ml_candidates(V, model, p, scans_per_pose=counts)
        else:
            cand = candidate_jacobian(V, model, p, near_singular_mm=margin * NEAR_SINGULAR_MM)
        k = max(min(n_select, int(cand.usable.sum())), model.n_free)
        sel = select_poses(
            cand.jacobian, k, criterion=criterion, max_condition=max_condition,
            information=cand.information,
        )  # fmt: skip
        if previous is not None and np.array_equal(sel.indices, previous):
            break  # the same poses again: the estimate would not change
        result = fit(sel.indices, p)
        previous, p = sel.indices, result.params
    # report against the caller's start, not the intermediate one of the last round
    return Calibration(replace(result, start=np.asarray(start, dtype=float)), sel, rounds_run)


def calibrate_scans(
    volts: np.ndarray,
    model: ParameterModel = PAPER7,
    start: np.ndarray = NOMINAL,
    *,
    noise_volts: float | np.ndarray | None = None,
) -> Calibration:
    """Identify the parameters by maximum likelihood from single scans, every one a pose.

    Parameters
    ----------
    volts : array_like, shape (N, 4)
        Readings of single scans, moving or still, V, each brought to its scan's instant
        (:func:`loopcal.calibration.scans.deskew`).
    model : ParameterModel, default PAPER7
        Which parameters are free, tied and fixed.
    start : array_like, shape (20,), default NOMINAL
        Full parameter vector to start from (mm, mm/V).
    noise_volts : float or array_like, shape (4,), optional
        Known noise of one reading, 1 sigma, V; None estimates it from the misfit.

    Returns
    -------
    Calibration
        The identification (one rotation per scan, :func:`identify` with ``method="ml"``),
        no selection, one round.

    Raises
    ------
    InputError, ParameterError, UnobservableError, ConvergenceError
        As :func:`identify`.

    Notes
    -----
    No pose is selected: with one rotation per scan eliminated in closed form
    (:mod:`loopcal.calibration.implicit`), a fit on 10,000 scans costs a fraction of a
    second, and every scan adds information. Scans whose rotation the lengths do not
    determine are left out by :func:`identify`.
    """
    ident = identify(volts, model, start, method="ml", noise_volts=noise_volts)
    return Calibration(replace(ident, start=np.asarray(start, dtype=float)), None, 1)
