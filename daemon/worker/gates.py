"""The acceptance gates: when the worker may vouch for a calibration, and what to do if not.

Each gate compares one figure of the identification with a limit and, when it fails, says
why in plain words and what the technician should do about it. ``loopcal calibrate --write``
writes the controller config only if every gate passes. The limits (docs/calibration.md
explains each):

=================  ===========================================================================
gate               passes when
=================  ===========================================================================
``poses``          at least MIN_POSES still poses (a fit on every scan: distinct positions),
                   and every channel moved across them
``converged``      the identification converged
``condition``      condition number of the scaled Jacobian <= 1000
``min_singular``   its smallest singular value >= MIN_SINGULAR
``noise``          the residuals imply no more noise than NOISE_RATIO x the noise the poses'
                   own spread predicts (their loops close as well as the sensors allow)
``averaging``      (a fit on every scan) its misfit averages down over a second of motion as
                   noise does
``gains``          (a fit on every scan) no fixed gain would fit the scans better if freed
``holdout``        poses kept out of the fit close their loops as well as predicted
``plausible``      no parameter moved further than a refit, or a blueprint tolerance, can
``precision``      every identified parameter's standard deviation is within PRECISION
=================  ===========================================================================
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from statistics import NormalDist

import numpy as np

from loopcal.calibration.observability import CONDITION_OK
from loopcal.calibration.parameters import GAIN_NOMINAL, INDEX, UNITS, ParameterModel
from loopcal.calibration.poses import pose_noise_volts
from loopcal.calibration.residuals import loop_residuals, noise_directions, reference_points
from loopcal.calibration.simulate import NEAR_SINGULAR_MM

MIN_POSES = 30  #: still poses the ``poses`` gate needs at least
MIN_CHANNEL_RANGE_V = 0.5  #: V; a channel that moves less than this over all poses is stuck
BARELY_MOVED_V = 2.0  #: V; every channel within this over all poses, the plate barely moved
POSITION_CELL_V = 1.0  #: V; scans count as distinct positions this far apart on a channel
MIN_SINGULAR = 0.05  #: smallest minimum singular value of the scaled Jacobian
NOISE_RATIO = 1.5  #: largest fitted noise over the noise the poses predict
HOLDOUT_EVERY = 5  #: every fifth pose is kept out of the fit to validate it
HOLDOUT_BLOCK_S = 5.0  #: a fit on every scan keeps every fifth stretch of this long out
AVERAGING_S = 1.0  #: s; the averaging gate's windows of consecutive scans
#: allowance over the chi-square bound of the averaging gate (the misfit is not quite white:
#: the fitted rotations and parameters take a little of it)
AVERAGING_MARGIN = 1.15
#: allowance over the chi-square bound, since the predicted noise is itself estimated and
#: the parameters' own uncertainty adds to the held-out poses' errors
HOLDOUT_MARGIN = 1.15
#: largest believable change per parameter group (a refitted LVDT moves its offset by mm)
CHANGE_LIMITS = {"offset": 15.0, "geometry": 3.0, "gain": 0.05}
#: largest standard deviation of an identified parameter, by unit
PRECISION = {"mm": 0.25, "mm/V": 0.01}


@dataclass(frozen=True)
class Gate:
    """One acceptance check's result: what was compared, and if it failed, why and what to do.

    Every gate function returns one; ``loopcal calibrate --json`` prints them as
    ``{"name", "passed", "value", "limit", "reason", "advice"}`` (:meth:`as_dict`).

    Attributes
    ----------
    name : str
        The gate: ``"poses"``, ``"converged"``, ``"condition"``, ``"min_singular"``,
        ``"noise"``, ``"holdout"``, ``"plausible"`` or ``"precision"``.
    passed : bool
        Whether the check passed.
    value : float, int, str or None
        What was compared, for people and JSON (a count, a ratio, or a text with its unit
        such as ``"12.34 mV"``).
    limit : str
        The limit it was compared with, as text (e.g. ``"<= 1000"``).
    reason : str, default ""
        Why it failed, in plain words; empty when it passed.
    advice : str, default ""
        What the technician should do about it; empty when it passed.
    """

    name: str
    passed: bool
    value: float | int | str | None
    limit: str
    reason: str = ""
    advice: str = ""

    def as_dict(self) -> dict:
        """The gate as JSON-ready fields.

        Returns
        -------
        dict
            ``{"name", "passed", "value", "limit", "reason", "advice"}``.
        """
        return asdict(self)

    def line(self) -> str:
        """The gate for people: ``  [pass] name: value (limit ...)``.

        Returns
        -------
        str
            One line; a failed gate adds a ``why:`` line and a ``do:`` line. A float value
            is shown to 4 significant digits.
        """
        mark = "pass" if self.passed else "FAIL"
        value = f"{self.value:.4g}" if isinstance(self.value, float) else str(self.value)
        text = f"  [{mark}] {self.name}: {value} (limit {self.limit})"
        if not self.passed:
            text += f"\n         why: {self.reason}\n         do:  {self.advice}"
        return text


def _group(name: str) -> str:
    if name.startswith("d0"):
        return "offset"
    if name.startswith("S"):
        return "gain"
    return "geometry"


#: advice for a failing gate, the text or a function that makes it (called only on failure:
#: :func:`loopcal.daemon.worker.coverage.lazy_coverage_advice`)
Advice = str | Callable[[], str]


def _text(advice: Advice) -> str:
    return advice if isinstance(advice, str) else advice()


# ---------------------------------------------------------------------------- gates


def _motion_failure(
    span: np.ndarray, n: int, over: str, move: str, unit: str = "poses"
) -> Gate | None:
    """The ``poses`` gate's failure when the plate barely moved or a channel never did
    (span: (4,) each channel's range, V; n: the gate's value; over: what the ranges are
    over, as text; move: the advice to move; unit: what the gate counts), else None."""
    if span.max() < BARELY_MOVED_V:
        return Gate(
            "poses",
            False,
            n,
            f">= {MIN_POSES} {unit}, every channel moving",
            f"the plate barely moved: every channel stayed within {span.max():.2f} V "
            f"({span.max() * GAIN_NOMINAL:.1f} mm of stroke) over {over}",
            move,
        )
    stuck = [i + 1 for i in range(4) if span[i] < MIN_CHANNEL_RANGE_V]
    if stuck and len(stuck) < 4:
        names = ", ".join(f"sensor {i}" for i in stuck)
        return Gate(
            "poses",
            False,
            n,
            f">= {MIN_POSES} {unit}, every channel moving",
            f"{names} read the same ({', '.join(f'{span[i - 1]:.3f} V' for i in stuck)} "
            f"range) over {over} while the others moved: stuck or disconnected",
            f"check {names}: its LVDT core, cable and conditioner; then record again",
        )
    return None


def poses_gate(volts: np.ndarray) -> Gate:
    """Enough still poses, and no channel that never moved (stuck or disconnected).

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        Mean readings of every still pose found, V.

    Returns
    -------
    Gate
        ``"poses"``, its value the number of poses k.

    Notes
    -----
    Fails, in this order, when the plate barely moved (every channel's range over the
    poses under :data:`BARELY_MOVED_V`, 2 V, about 7.5 mm of stroke at the nominal gain),
    when some but not all channels moved less than :data:`MIN_CHANNEL_RANGE_V` (0.5 V:
    stuck or disconnected, named), and when there are fewer than :data:`MIN_POSES` (30)
    poses. The limits are docs/calibration.md's "poses" gate.
    """
    n = len(volts)
    if n:
        failed = _motion_failure(
            np.ptp(volts, axis=0), n, f"all {n} still poses",
            "move the plate by hand through its whole range (tilt it 25 deg or more "
            "toward each sensor), holding each position still for about a second",
        )  # fmt: skip
        if failed is not None:
            return failed
    if n < MIN_POSES:
        return Gate(
            "poses",
            False,
            n,
            f">= {MIN_POSES}",
            f"only {n} still poses found in the recording",
            "move the plate to at least 40 positions, holding each still for about a second",
        )
    return Gate("poses", True, n, f">= {MIN_POSES}")


def distinct_positions(volts: np.ndarray) -> int:
    """How many distinct positions scans passed through.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The scans' readings, V.

    Returns
    -------
    int
        The number of cells of :data:`POSITION_CELL_V` (1 V, about 4 mm of stroke) on
        every channel that the readings fall in; 0 for no scans.
    """
    if len(volts) == 0:
        return 0
    return len(np.unique(np.floor(volts / POSITION_CELL_V).astype(np.int64), axis=0))


def scans_gate(volts: np.ndarray, seconds: float) -> Gate:
    """Enough motion in the usable scans, and no channel that never moved: the ``poses``
    gate of a fit on every scan.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The readings of the usable scans, V.
    seconds : float
        The time those scans span at the scan rate, s (for the text).

    Returns
    -------
    Gate
        ``"poses"``, its value the number of distinct positions
        (:func:`distinct_positions`).

    Notes
    -----
    Fails, in this order, when the plate barely moved or a channel did not (as
    :func:`poses_gate`, with each channel's range taken between its 0.5th and 99.5th
    percentiles, so that a few wild readings do not count as motion), and when the scans
    passed through fewer than :data:`MIN_POSES` (30) distinct positions. Whether the motion
    holds enough information is the ``min_singular``, ``condition`` and ``precision``
    gates' judgement, on the fit itself.
    """
    n = len(volts)
    k = distinct_positions(volts)
    move = ("move the plate by hand through its whole range for about two minutes, tilting "
            "it 25 deg or more toward each sensor")  # fmt: skip
    if n:
        lo, hi = np.percentile(volts, [0.5, 99.5], axis=0)
        failed = _motion_failure(hi - lo, k, f"{seconds:.0f} s of usable scans", move, "positions")
        if failed is not None:
            return failed
    if k < MIN_POSES:
        return Gate(
            "poses",
            False,
            k,
            f">= {MIN_POSES} positions",
            f"the plate passed through only {k} distinct positions ({POSITION_CELL_V:g} V "
            f"apart) in {seconds:.0f} s of usable scans",
            move,
        )
    return Gate("poses", True, k, f">= {MIN_POSES} positions")


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
        :func:`~loopcal.daemon.worker.coverage.lazy_coverage_advice`).

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
    ok = condition <= CONDITION_OK
    return Gate(
        "condition",
        ok,
        condition,
        f"<= {CONDITION_OK:g}",
        "" if ok else "some combination of parameters is barely seen by these poses",
        "" if ok else _text(advice),
    )


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
    ok = s_min >= MIN_SINGULAR
    return Gate(
        "min_singular",
        ok,
        s_min,
        f">= {MIN_SINGULAR:g}",
        "" if ok else "the poses hardly tell some parameters apart",
        "" if ok else _text(advice),
    )


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
    ok = sigma_fit <= limit
    return Gate(
        "noise",
        ok,
        f"{1000 * sigma_fit:.2f} mV",
        f"<= {NOISE_RATIO:g} x {1000 * expected:.2f} mV = {1000 * limit:.2f} mV",
        ""
        if ok
        else f"the loops close only to {1000 * sigma_fit:.1f} mV of equivalent sensor "
        f"noise, where the readings' own scatter predicts {1000 * expected:.1f} mV",
        ""
        if ok
        else "check every sensor's wiring and its gain S in the controller config "
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
        ``AVERAGING_MARGIN * chi2_quantile(J, 0.001) / J``.

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
    limit = AVERAGING_MARGIN * chi2_quantile(windows, 0.001) / windows
    ok = ratio <= limit
    return Gate(
        "averaging",
        ok,
        ratio,
        f"<= {limit:.2f} (misfit variance of {AVERAGING_S:g}-s means x scans per window over "
        f"a scan's, {windows} windows)",
        ""
        if ok
        else f"the fit's misfit averages down over {AVERAGING_S:g} s of motion only "
        f"{1 / ratio:.2f} as much as noise would: something systematic is left in it",
        ""
        if ok
        else "check every sensor's gain S in the controller config (a replaced sensor), "
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
        ``chi2_quantile(len(names), 0.001)``.

    Notes
    -----
    Single scans see many more orientations than still poses, and so tell the parameters
    apart more sharply: a gain error that still poses could not see biases a fit on every
    scan by many of its own standard deviations (docs/calibration.md gives the figures). A
    wrong gain leaves a misfit that correlates with the gain's own information; this test
    looks for exactly that, and catches an error of about four of ``std``.
    """
    k = len(names)
    limit = chi2_quantile(k, 0.001)
    ok = statistic <= limit
    j = int(np.argmax(np.abs(change) / std))
    name = names[j]
    return Gate(
        "gains",
        ok,
        statistic,
        f"<= {limit:.1f} (chi-square, {k} fixed gains)",
        ""
        if ok
        else f"the loops would close better with {name} changed by {change[j]:+.4f} mm/V "
        f"(+-{std[j]:.4f}, {100 * change[j] / GAIN_NOMINAL:+.2f} %): sensor {name[1:]}'s "
        "gain in the config is wrong, or a parameter held fixed is",
        ""
        if ok
        else f"check sensor {name[1:]}'s gain {name} against its calibration sheet; if it "
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


def _log_upper_gamma(a: float, t: float) -> tuple[float, float]:
    """log Q(a, t), the regularized upper incomplete gamma function, and its derivative
    with respect to t, by the continued fraction (modified Lentz; it converges quickly for
    t > a + 1, where the upper tail's quantiles lie for every a but the smallest)."""
    tiny = 1e-300
    b = t + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / (b if abs(b) >= tiny else tiny)
    h = d
    for i in range(1, 100_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-16:
            break
    log_density = -t + (a - 1.0) * math.log(t) - math.lgamma(a)  # d(-Q)/dt
    log_q = log_density + math.log(t) + math.log(h)
    return log_q, -math.exp(log_density - log_q)


def chi2_quantile(dof: int, tail: float) -> float:
    """The upper ``tail`` quantile of the chi-square distribution with ``dof`` degrees.

    The value a chi-square variable of ``dof`` degrees of freedom exceeds with probability
    ``tail``, as ``scipy.special.chdtri(dof, tail)`` gives it (scipy.special costs a fifth
    of a second to import): Newton's method on log Q(dof / 2, x / 2) from the
    Wilson-Hilferty approximation (tests/daemon/worker/test_gates.py compares the two).

    Parameters
    ----------
    dof : int
        Degrees of freedom, >= 1.
    tail : float
        The upper tail's probability, 0 < tail <= 0.1.

    Returns
    -------
    float
        The upper ``tail`` quantile of chi-square with ``dof`` degrees of freedom.

    Raises
    ------
    ValueError
        If ``dof`` < 1 or ``tail`` is outside (0, 0.1].
    """
    if not (dof >= 1 and 0.0 < tail <= 0.1):
        raise ValueError(f"chi2_quantile needs dof >= 1 and 0 < tail <= 0.1, got {dof}, {tail}")
    a, target = dof / 2.0, math.log(tail)
    z = NormalDist().inv_cdf(1.0 - tail)
    q = 2.0 / (9.0 * dof)
    t = max(a, 0.5 * dof * (1.0 - q + z * math.sqrt(q)) ** 3)
    last = math.inf
    for _ in range(100):
        log_q, slope = _log_upper_gamma(a, t)
        t_new = max(t - (log_q - target) / slope, 0.5 * t)
        moved = abs(t_new - t)
        t = t_new
        # quadratic convergence until rounding: stop at a step of a few ulps, or one no
        # smaller than the step before
        if moved <= 1e-14 * t or moved >= last:
            break
        last = moved
    return 2.0 * t


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
    The limit is ``HOLDOUT_MARGIN * sqrt(chi2_quantile(n, 0.001) / n)``: at the true
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
    limit = HOLDOUT_MARGIN * float(np.sqrt(chi2_quantile(n, 0.001) / n))  # chi2(n) 99.9 %
    ok = rms <= limit
    where = (f"{n} poses" if blocks is None
             else f"{n} scans in {blocks} stretches of {HOLDOUT_BLOCK_S:g} s")  # fmt: skip
    return Gate(
        "holdout",
        ok,
        rms,
        f"<= {limit:.2f} (RMS in predicted standard deviations, {where})",
        ""
        if ok
        else f"{where} kept out of the fit open their loops {rms:.1f} times as wide "
        "as their noise predicts: the fit describes its own "
        f"{'poses' if blocks is None else 'motion'}, not the mechanism",
        ""
        if ok
        else "free the parameters that changed (for example the gain of a replaced "
        "sensor) or check the mechanism for play"
        + ("; hold each position still" if blocks is None else ""),
    )


def plausible_gate(free: list[str], previous: np.ndarray, new: np.ndarray) -> Gate:
    """No parameter moved further than a refit, or a blueprint tolerance, can explain.

    Parameters
    ----------
    free : list of str
        The identified parameters' names (:data:`loopcal.calibration.parameters.NAMES`).
    previous : ndarray of float, shape (20,)
        The parameters before (the controller config's), mm and mm/V.
    new : ndarray of float, shape (20,)
        The identified parameters, likewise.

    Returns
    -------
    Gate
        ``"plausible"``, its value the change of the parameter closest to its limit
        (name, change and unit; ``"no change"`` when none changed), passed when every
        change is within its limit.

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
    return Gate(
        "plausible",
        False,
        f"{worst} {change:+.3f} {UNITS[worst]}",
        "changes within " + _limits_text(),
        f"{worst} would change by {change:+.3f} {UNITS[worst]}, more than a "
        f"{'refitted LVDT' if sensor else 'blueprint tolerance'} explains",
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
    ok = ratios[j] <= 1.0
    name = free[j]
    limit = f"<= {limits['mm']:g} mm, {limits['mm/V']:g} mm/V"
    return Gate(
        "precision",
        ok,
        f"{name} {std[j]:.3f} {UNITS[name]}",
        limit,
        "" if ok else f"{name} is known only to +-{std[j]:.3f} {UNITS[name]} (1 sigma)",
        "" if ok else _text(advice) + _for_how_long(seconds, ratios[j]),
    )


def _for_how_long(seconds: float | None, ratio: float) -> str:
    """``precision_gate``'s "for how long" (ratio: the worst std over its limit, > 1)."""
    if seconds is None or not (np.isfinite(ratio) and seconds > 0):
        return ""
    more = seconds * (ratio**2 - 1.0)
    if more > 3600:
        return "; at this pace it would take over an hour more: move the plate further"
    return f", for about {max(5, 5 * math.ceil(more / 5)):.0f} s more of such motion"
