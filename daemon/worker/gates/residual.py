"""The gates on how the loops close: as well as the sensors' noise allows, with nothing
systematic left in the misfit, with every fixed gain right, and on samples the fit never saw.

``noise``, ``averaging``, ``gains`` and ``holdout``; docs/calibration.md gives the limits.
"""

from __future__ import annotations

import numpy as np

from loopcal.calibration.parameters import GAIN_NOMINAL, ParameterModel
from loopcal.calibration.poses import pose_noise_volts
from loopcal.calibration.residuals import loop_residuals, noise_directions, reference_points
from loopcal.calibration.simulate import NEAR_SINGULAR_MM

from .chi2 import chi2_quantile
from .gate import Gate

NOISE_RATIO = 1.5  #: largest fitted noise over the noise the poses predict
HOLDOUT_EVERY = 5  #: every fifth pose is kept out of the fit to validate it
HOLDOUT_BLOCK_S = 5.0  #: a fit on every scan keeps every fifth stretch of this long out
AVERAGING_S = 1.0  #: s; the averaging gate's windows of consecutive scans
#: the upper tail of chi-square beyond the averaging, gains and holdout gates' bounds: each
#: fails a right fit once in a thousand
CHI2_TAIL = 0.001
#: allowance over the chi-square bound of the averaging gate (the misfit is not quite white:
#: the fitted rotations and parameters take a little of it)
AVERAGING_MARGIN = 1.15
#: allowance over the chi-square bound, since the predicted noise is itself estimated and
#: the parameters' own uncertainty adds to the held-out poses' errors
HOLDOUT_MARGIN = 1.15


def expected_noise(scan_noise: np.ndarray, counts: np.ndarray, *, per_scan: bool = False) -> float:
    """RMS noise of the poses' mean readings the poses themselves predict.

    Parameters
    ----------
    scan_noise : ndarray of float, shape (k, 4)
        Each pose's noise of one scan per channel, V (from its scan-to-scan differences).
    counts : ndarray of int, shape (k,)
        Scans averaged into each pose.
    per_scan : bool, default False
        Give it as the noise of one scan (each pose's variance times its scan count), as
        the maximum-likelihood fit reports its noise; else as the noise of a pose's mean
        reading, as the paper's method does.

    Returns
    -------
    float
        The RMS over poses and channels, V:
        :func:`loopcal.calibration.poses.pose_noise_volts` (``sqrt(scan_noise^2 / count +
        LSB^2 / 12)``, the 12-bit rounding included), per scan if asked.
    """
    var = pose_noise_volts(scan_noise, counts) ** 2
    if per_scan:
        var = var * counts[:, None]
    return float(np.sqrt(var.mean()))


def noise_gate(sigma_fit: float, expected: float, *, still: bool = True) -> Gate:
    """The loops close as well as the sensors allow: the fit's noise <= 1.5 x the expected.

    Parameters
    ----------
    sigma_fit : float
        The noise the identification's residuals imply, V (per scan for maximum
        likelihood, per pose for the paper's method).
    expected : float
        The noise the poses' own scan-to-scan scatter predicts, V, on the same footing
        (:func:`expected_noise`); for a fit on every scan, the noise of one reading from
        fourth differences (:func:`loopcal.calibration.scans.difference_noise`).
    still : bool, default True
        The fit used still poses (the advice then asks to hold them still).

    Returns
    -------
    Gate
        ``"noise"``, passed when ``sigma_fit <= NOISE_RATIO * expected``; its value is
        ``sigma_fit`` in mV, as text.

    Notes
    -----
    :data:`NOISE_RATIO` (1.5, docs/calibration.md): 40 simulated sessions at 40 mV gave a
    ratio of 0.93 on average and at most 1.17. It fails for a wrong gain (about 3 % or
    more), a swapped or sticking channel, or a parameter missing from the free set.
    """
    limit = NOISE_RATIO * expected
    return Gate.judged(
        "noise",
        sigma_fit <= limit,
        f"{1000 * sigma_fit:.2f} mV",
        f"<= {NOISE_RATIO:g} x {1000 * expected:.2f} mV = {1000 * limit:.2f} mV",
        f"the loops close only to {1000 * sigma_fit:.1f} mV of equivalent sensor "
        f"noise, where the readings' own scatter predicts {1000 * expected:.1f} mV",
        "check every sensor's wiring and its gain S in the controller config "
        "(a swapped, sticking or mis-scaled channel)"
        + (", and hold the plate still in each pose" if still else ""),
    )


def averaging_gate(ratio: float, windows: int) -> Gate:
    """A fit on every scan: its misfit averages down over a second of neighbouring scans
    as sensor noise does, so nothing systematic is left in it.

    Parameters
    ----------
    ratio : float
        ``window * mean(window means^2) / mean(misfit^2)`` of the fitted scans' loop
        misfits over :data:`AVERAGING_S` windows
        (:func:`loopcal.calibration.scans.averaging_ratio`), dimensionless.
    windows : int
        How many whole windows.

    Returns
    -------
    Gate
        ``"averaging"``, passed when ``ratio`` is within
        ``AVERAGING_MARGIN * chi2_quantile(J, CHI2_TAIL) / J``.

    Notes
    -----
    White noise averages down: the ratio is then about 1 (``J * ratio`` is chi-square with
    J degrees of freedom). A model error (a wrong gain, a parameter missing from the free
    set, a sticking channel) leaves a misfit b that changes slowly along the motion and
    does not average down: the ratio grows as ``1 + (w - 1) b^2 / (sigma^2 + b^2)`` for
    windows of w scans. Still poses averaged the same way before the fit, which is what
    made the noise gate sensitive to a wrong gain; a fit on single scans needs this gate
    for it (docs/calibration.md).
    """
    if windows < 5 or not np.isfinite(ratio):
        return Gate(
            "averaging", False, windows, ">= 5 windows",
            f"only {windows} stretches of {AVERAGING_S:g} s of consecutive scans to judge "
            "the misfit by",
            "record for longer, without interruptions",
        )  # fmt: skip
    limit = AVERAGING_MARGIN * chi2_quantile(windows, CHI2_TAIL) / windows
    return Gate.judged(
        "averaging",
        ratio <= limit,
        ratio,
        f"<= {limit:.2f} (misfit variance of {AVERAGING_S:g}-s means x scans per window over "
        f"a scan's, {windows} windows)",
        # made only on failure: a ratio that passed may be 0
        lambda: f"the fit's misfit averages down over {AVERAGING_S:g} s of motion only "
        f"{1 / ratio:.2f} as much as noise would: something systematic is left in it",
        "check every sensor's gain S in the controller config (a replaced sensor), "
        "its wiring, and whether a channel sticks; or free the parameters that may have "
        "changed",
    )


def gains_gate(names: list[str], statistic: float, change: np.ndarray, std: np.ndarray) -> Gate:
    """A fit on every scan: the fixed gains fit the scans, so none is wrong enough to bias
    the result (the score test of :func:`loopcal.calibration.implicit.score_test`).

    Parameters
    ----------
    names : list of str
        The gains held fixed (of S1..S4).
    statistic : float
        The test statistic, dimensionless: chi-square with ``len(names)`` degrees of freedom
        when every fixed gain is right.
    change, std : ndarray of float, shape (len(names),)
        Each gain's change if it were freed (one Gauss-Newton step) and its standard
        deviation then, mm/V.

    Returns
    -------
    Gate
        ``"gains"``, its value the statistic, passed when it is within
        ``chi2_quantile(len(names), CHI2_TAIL)``.

    Notes
    -----
    Single scans see many more orientations than still poses, and so tell the parameters
    apart more sharply: a gain error that still poses could not see biases a fit on every
    scan by many of its own standard deviations (docs/calibration.md gives the figures). A
    wrong gain leaves a misfit that correlates with the gain's own information; this test
    looks for exactly that, and catches an error of about four of ``std``.
    """
    k = len(names)
    limit = chi2_quantile(k, CHI2_TAIL)
    j = int(np.argmax(np.abs(change) / std))
    name = names[j]
    return Gate.judged(
        "gains",
        statistic <= limit,
        statistic,
        f"<= {limit:.1f} (chi-square, {k} fixed gains)",
        f"the loops would close better with {name} changed by {change[j]:+.4f} mm/V "
        f"(+-{std[j]:.4f}, {100 * change[j] / GAIN_NOMINAL:+.2f} %): sensor {name[1:]}'s "
        "gain in the config is wrong, or a parameter held fixed is",
        f"check sensor {name[1:]}'s gain {name} against its calibration sheet; if it "
        "is right, free the parameters that may have changed (a fixed geometry value, or "
        f"{name} itself: --free with {name} added)",
    )


def holdout_residuals(
    volts: np.ndarray,
    params: np.ndarray,
    noise: np.ndarray | None = None,
    *,
    model: ParameterModel | None = None,
    covariance: np.ndarray | None = None,
) -> np.ndarray:
    """Loop-closure error of each pose at ``params``, near-singular poses left out.

    Parameters
    ----------
    volts : ndarray of float, shape (m, 4)
        The poses' mean readings, V.
    params : ndarray of float, shape (20,)
        The parameters to close the loops with (mm, mm/V).
    noise : ndarray of float, shape (m, 4), optional
        The standard deviation of each pose's mean reading per channel, V
        (:func:`loopcal.calibration.poses.pose_noise_volts`).
    model : ParameterModel, optional
        The fit's free parameters and ties; with ``covariance``.
    covariance : ndarray of float, shape (n_free, n_free), optional
        The fitted free parameters' covariance; with ``model``.

    Returns
    -------
    ndarray of float, shape (m',)
        One error per pose that is feasible and not near-singular (m' <= m; empty for no
        poses): without ``noise``, in volts of equivalent sensor noise (the residuals
        projected on their noise direction); with it, in units of the error's own
        predicted standard deviation, N(0, 1) each when the parameters are right. With
        ``model`` and ``covariance`` the prediction includes the parameters' own
        uncertainty (poses that were not in the fit: held out).
    """
    if len(volts) == 0:
        return np.zeros(0)
    ref = reference_points(volts, params)
    with_jac = model is not None and covariance is not None
    r = loop_residuals(
        params, volts, ref, jacobian=with_jac, directions=model.tie_matrix if with_jac else None
    )
    ok = r.feasible.all(axis=1) & (r.separation.min(axis=1) >= NEAR_SINGULAR_MM)
    if not ok.any():
        return np.zeros(0)
    u, s, v = noise_directions(params, volts[ok], ref[ok])
    w = np.einsum("mi,mi->m", u, r.residuals[ok]) / s
    if noise is None:
        return w
    var = np.einsum("mi,mi->m", v**2, noise[ok] ** 2)
    if with_jac:
        g = np.einsum("mi,min->mn", u, r.jacobian[ok]) / s[:, None]  # d w / d x
        var = var + np.einsum("mn,nq,mq->m", g, covariance, g)
    return w / np.sqrt(var)


def holdout_gate(z: np.ndarray, *, blocks: int | None = None) -> Gate:
    """Poses kept out of the fit close their loops as well as predicted.

    Parameters
    ----------
    z : ndarray of float, shape (n,)
        The held-out poses' loop-closure errors over their predicted standard deviations
        (:func:`holdout_residuals` with ``noise``, ``model`` and ``covariance``),
        dimensionless.
    blocks : int, optional
        For a fit on every scan: z is one per held-out scan, from this many held-out
        stretches of time (the text counts scans and stretches); None: one per pose.

    Returns
    -------
    Gate
        ``"holdout"``: failed for fewer than 5 poses (its value n); else its value the RMS
        of ``z``, passed when that is within the limit.

    Notes
    -----
    The limit is ``HOLDOUT_MARGIN * sqrt(chi2_quantile(n, CHI2_TAIL) / n)``: at the true
    parameters ``z`` is N(0, 1) per pose, so ``n * rms^2`` is chi-square with n degrees
    of freedom, and its 99.9 % bound, times :data:`HOLDOUT_MARGIN` (1.15: the predicted
    noise is itself estimated), is about 2.0 for 9 poses. One pose in
    :data:`HOLDOUT_EVERY` (5) is held out. It fails when the fit describes its own poses, not the
    mechanism (docs/calibration.md).
    """
    n = len(z)
    what = "poses" if blocks is None else "scans"
    if n < 5 or blocks == 0:
        return Gate(
            "holdout",
            False,
            n,
            f">= 5 held-out {what}",
            f"only {n} {what} were left to check the fit against",
            "record more still positions" if blocks is None else "record for longer",
        )
    rms = float(np.sqrt(np.mean(z**2)))
    limit = HOLDOUT_MARGIN * float(np.sqrt(chi2_quantile(n, CHI2_TAIL) / n))
    where = (f"{n} poses" if blocks is None
             else f"{n} scans in {blocks} stretches of {HOLDOUT_BLOCK_S:g} s")  # fmt: skip
    return Gate.judged(
        "holdout",
        rms <= limit,
        rms,
        f"<= {limit:.2f} (RMS in predicted standard deviations, {where})",
        f"{where} kept out of the fit open their loops {rms:.1f} times as wide "
        "as their noise predicts: the fit describes its own "
        f"{'poses' if blocks is None else 'motion'}, not the mechanism",
        "free the parameters that changed (for example the gain of a replaced "
        "sensor) or check the mechanism for play"
        + ("; hold each position still" if blocks is None else ""),
    )
