"""Single scans as calibration samples: the channel skew taken out, and the sensor noise
measured on a moving plate (docs/model.md section 9.1).

The module converts its four channels one after another, channel i (0-based) at
``t + i * skew_s`` after the scan's time stamp t (250 µs apart). While the plate moves,
the four readings of one scan therefore belong to four slightly different orientations.
Each reading is brought to the scan's own instant with the rate of change of its channel
between the neighbouring scans::

    V'_ki = V_ki - i * skew_s * dV_i/dt (t_k),

the derivative by central differences over the scans k - 1 and k + 1 (one-sided at the
ends of a run of consecutive scans). Since a reading is a smooth function of the plate's
rotation, this is to first order the same as predicting channel i from the rotation
``exp([w_k i skew_s]x) R_k`` with w_k the rotation rate between the neighbouring scans, and
it leaves the fit's model unchanged. It adds almost no noise: channel 4's correction weighs
the neighbours' noise by ``3 * 250 µs / (2 * 50 ms) = 0.0075`` at 20 Hz.

Noise that motion does not inflate: fourth differences ``V[k-2] - 4 V[k-1] + 6 V[k] -
4 V[k+1] + V[k+2]`` cancel every cubic trend over five scans (a hand's motion at 20 Hz) and
leave white noise of variance ``70 sigma^2``; the median absolute difference, scaled
(``1.4826 / sqrt(70)``), ignores the few scans of a sudden jerk.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .residuals import check_volts

#: the datasheet's delay between the conversions of two neighbouring channels, s
CHANNEL_SKEW_S = 250e-6
#: weights of the fourth difference and their sum of squares
_D4 = np.array([1.0, -4.0, 6.0, -4.0, 1.0])
_D4_VAR = float(_D4 @ _D4)  # 70
#: the median absolute value of a standard normal, as a fraction of its standard deviation
_MAD_NORMAL = 0.6744897501960817


def _runs(starts: np.ndarray, n: int) -> np.ndarray:
    """Run id of each of n scans from the (sorted, unique) first rows of its runs."""
    run = np.zeros(n, dtype=np.int64)
    if len(starts):
        run[starts[(starts > 0) & (starts < n)]] = 1  # a start at n begins no scan's run
    return np.cumsum(run)


def _check(
    volts: np.ndarray, valid: np.ndarray | None, rows: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    V = check_volts(volts)
    n = len(V)
    ok = np.ones(n, dtype=bool) if valid is None else np.asarray(valid)
    if ok.shape != (n,) or ok.dtype != bool:
        raise InputError(f"valid must be {n} booleans, one per scan")
    at = np.flatnonzero(ok) if rows is None else np.asarray(rows)
    if at.ndim != 1 or not np.issubdtype(at.dtype, np.integer):
        raise InputError("rows must be one dimension of row numbers")
    if len(at) and (at.min() < 0 or at.max() >= n or not ok[at].all()):
        raise InputError(f"rows must be valid rows of the {n} scans")
    return V, ok, at.astype(np.int64)


def deskew(
    volts: np.ndarray,
    period_s: float,
    *,
    valid: np.ndarray | None = None,
    rows: np.ndarray | None = None,
    skew_s: float = CHANNEL_SKEW_S,
) -> tuple[np.ndarray, np.ndarray]:
    """Readings brought to their scan's time stamp (the module docstring's correction).

    Parameters
    ----------
    volts : array_like, shape (n, 4)
        Readings of consecutive scans, V, oldest first (row j + 1 is ``period_s`` after
        row j).
    period_s : float
        Time between two consecutive scans, s (0.05 at 20 Hz).
    valid : array_like of bool, shape (n,), optional
        Which scans may be used, as readings and as neighbours; default all.
    rows : array_like of int, shape (k,), optional
        The (valid) rows to correct; default every valid row.
    skew_s : float, default CHANNEL_SKEW_S
        Delay between two neighbouring channels' conversions, s.

    Returns
    -------
    volts : ndarray, shape (k, 4)
        ``V_ki - i * skew_s * dV_i/dt`` of the rows, V; the rate from the valid neighbours
        (central where both are, one-sided where one is).
    corrected : ndarray of bool, shape (k,)
        False for a row with no valid neighbour (its readings are returned as they are).

    Raises
    ------
    InputError
        Bad readings, mask or rows, or a period that is not positive and finite.
    """
    V, ok, at = _check(volts, valid, rows)
    if not (np.isfinite(period_s) and period_s > 0):
        raise InputError(f"period_s must be positive, got {period_s!r}")
    n = len(V)
    has_prev = (at > 0) & ok[np.maximum(at - 1, 0)]
    has_next = (at < n - 1) & ok[np.minimum(at + 1, n - 1)]
    prev = np.where(has_prev, at - 1, at)
    nxt = np.where(has_next, at + 1, at)
    steps = (nxt - prev).astype(float)
    corrected = steps > 0
    rate = np.zeros((len(at), 4))
    c = corrected
    rate[c] = (V[nxt[c]] - V[prev[c]]) / (steps[c, None] * period_s)
    return V[at] - rate * (np.arange(4) * skew_s), corrected


def difference_noise(
    volts: np.ndarray, *, valid: np.ndarray | None = None, rows: np.ndarray | None = None
) -> np.ndarray:
    """Per-channel noise of one reading, from fourth differences (module docstring): robust
    to motion and to occasional jerks.

    Parameters
    ----------
    volts : array_like, shape (n, 4)
        Readings of consecutive scans, V.
    valid : array_like of bool, shape (n,), optional
        Which scans may be used; a fourth difference needs five valid scans in a row.
    rows : array_like of int, optional
        The (valid) rows to centre the differences on; default every valid row.

    Returns
    -------
    ndarray, shape (4,)
        1 sigma per channel, V; NaN where no row has its five scans.
    """
    V, ok, at = _check(volts, valid, rows)
    n = len(V)
    if n < 5 or not len(at):
        return np.full(4, np.nan)
    centre = at[(at >= 2) & (at <= n - 3)]
    whole = np.all([ok[centre + j] for j in (-2, -1, 1, 2)], axis=0) if len(centre) else []
    centre = centre[whole] if len(centre) else centre
    if not len(centre):
        return np.full(4, np.nan)
    d = sum(w * V[centre + j - 2] for j, w in enumerate(_D4))
    return np.median(np.abs(d), axis=0) / (_MAD_NORMAL * np.sqrt(_D4_VAR))


def closure_misfit(volts: np.ndarray, rotations: np.ndarray, params: np.ndarray) -> np.ndarray:
    """Each scan's misfit along its loop direction: the part of its readings that no plate
    rotation explains, at given rotations and parameters.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        Readings, V.
    rotations : ndarray, shape (m, 3, 3)
        The scans' plate rotations (the fit's).
    params : ndarray, shape (20,)
        Full parameter vector (mm, mm/V).

    Returns
    -------
    ndarray, shape (m,)
        ``q_k . (V_k - Vhat_k)``, V, with q_k the unit vector orthogonal to the rotation
        Jacobian's columns (:func:`loopcal.calibration.implicit.loop_direction`). Its sign
        convention (the generalised cross product of the columns) is continuous along a
        motion, so the misfits of neighbouring scans can be averaged.
    """
    from .implicit import linearise, loop_direction

    V = check_volts(volts)
    lin = linearise(V, np.ones_like(V), rotations, params, np.zeros((20, 1)))
    q = loop_direction(np.moveaxis(lin.Jr, -1, 0).transpose(0, 2, 1))
    return np.einsum("mi,im->m", q, lin.r)


def averaging_ratio(
    misfit: np.ndarray, run_starts: np.ndarray | None, window: int
) -> tuple[float, int]:
    """How much less the misfit averages down over windows of neighbouring scans than
    white noise would.

    Parameters
    ----------
    misfit : array_like, shape (m,)
        One misfit per scan (:func:`closure_misfit`), in time order.
    run_starts : array_like of int, optional
        First row of each run of consecutive scans; windows never span two runs.
    window : int
        Scans per window, >= 2.

    Returns
    -------
    ratio : float
        ``window * mean(window means^2) / mean(misfit^2)``: about 1 for white noise (then
        ``J * ratio`` is about chi-square with J degrees of freedom), ``1 + (window - 1)
        b^2 / (sigma^2 + b^2)`` for a systematic misfit b that varies slowly along the
        motion; NaN for no whole window.
    windows : int
        J, the whole windows.
    """
    s = np.asarray(misfit, dtype=float)
    if s.ndim != 1 or window < 2:
        raise InputError("misfit must be one dimension and window at least 2")
    starts = np.zeros(1, dtype=np.int64) if run_starts is None else np.asarray(run_starts)
    run = _runs(np.unique(starts.astype(np.int64)), len(s))
    # position of each scan within its run; windows are [0, w), [w, 2w), ... of each run
    first = np.flatnonzero(np.diff(run, prepend=-1) != 0)
    pos = np.arange(len(s)) - np.repeat(first, np.diff(np.append(first, len(s))))
    win = pos // window
    key = run * (len(s) + 1) + win
    _, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    sums = np.bincount(inv, weights=s)
    whole = counts == window
    J = int(whole.sum())
    if J == 0 or not np.any(s):
        return float("nan"), J
    means = sums[whole] / window
    in_whole = whole[inv]
    return float(window * np.mean(means**2) / np.mean(s[in_whole] ** 2)), J
