"""Select the best poses of a recording and identify the parameters from them."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .identify import Identification, identify
from .observability import CONDITION_OK
from .parameters import NOMINAL, PAPER7, ParameterModel
from .residuals import check_volts
from .selection import Selection, candidate_jacobian, select_poses
from .simulate import NEAR_SINGULAR_MM


@dataclass(frozen=True)
class Calibration:
    """identification: the final estimate (from the selected poses); selection: the chosen
    poses, indices into the recording; rounds: how many select-and-identify rounds ran."""

    identification: Identification
    selection: Selection
    rounds: int


def calibrate(
    volts: np.ndarray,
    model: ParameterModel = PAPER7,
    start: np.ndarray = NOMINAL,
    *,
    n_select: int = 50,
    criterion: str = "min_singular",
    max_condition: float = CONDITION_OK,
    rounds: int = 2,
    noise_volts: float | None = None,
) -> Calibration:
    """Choose ``n_select`` of the recorded poses (readings (N, 4) in V) and identify.

    The first round designs the selection at ``start``; each further round designs it again
    at the previous estimate, where the Jacobian (and which poses are near-singular) is
    closer to the truth, and identifies again. With N <= n_select every pose is used.
    """
    V = check_volts(volts)
    p = np.asarray(start, dtype=float)
    result: Identification | None = None
    previous: np.ndarray | None = None
    rounds_run = 0
    while rounds_run < max(rounds, 1):
        rounds_run += 1
        # candidates keep a wider margin from singularity than identification demands, so
        # that a chosen pose stays usable as the estimate moves
        cand = candidate_jacobian(V, model, p, near_singular_mm=1.5 * NEAR_SINGULAR_MM)
        k = max(min(n_select, int(cand.usable.sum())), model.n_free)
        sel = select_poses(
            cand.jacobian, k, criterion=criterion, max_condition=max_condition,
            information=cand.information,
        )  # fmt: skip
        if previous is not None and np.array_equal(sel.indices, previous):
            break  # the same poses again: the estimate would not change
        result = identify(V[sel.indices], model, p, noise_volts=noise_volts)
        previous, p = sel.indices, result.params
    # report against the caller's start, not the intermediate one of the last round
    return Calibration(replace(result, start=np.asarray(start, dtype=float)), sel, rounds_run)
