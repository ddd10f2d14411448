"""Closed-loop identification by Levenberg-Marquardt with column scaling (docs/model.md section 5).

Minimises ``f^T f`` over the free parameters, f the stacked loop residuals (mm^2) of m poses.
Each iteration solves the damped, column-scaled normal equations::

    (G^T G + lambda diag(G^T G)) ds = -G^T f,   G = g H,   dx = H ds,

with the analytic Jacobian g (implicit differentiation of the sphere equations) and
``H = diag(sqrt(M) / ||g_j||)`` (see :mod:`loopcal.calibration.observability`).

Covariance. The four residuals of a pose share that pose's four readings, so they are
correlated, and to first order they are one scalar loop-closure error seen four times: their
noise is ``D_k e_k`` with ``D_k = df_k/dV_k`` (4 x 4, nearly rank one) and ``e_k`` the voltage
noise. The least-squares estimate then has the sandwich covariance::

    C = (g^T g)^-1 (sum_k g_k^T D_k Sigma_V D_k^T g_k) (g^T g)^-1,

with ``Sigma_V = sigma_V^2 I``. ``sigma_V`` is the given noise level or, by default, estimated
from the whitened residuals ``u_k^T f_k / s_k`` (``s_k u_k v_k^T`` the leading singular triple
of ``D_k``), which have variance ``sigma_V^2`` each.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import implicit
from .damping import Damping
from .defaults import DEFAULT_METHOD, METHODS
from .errors import ConvergenceError, InputError
from .observability import (
    CONDITION_OK,
    ObservabilityIndices,
    column_scales,
    require_observable,
)
from .parameters import (
    NOMINAL,
    PAPER7,
    STROKE_MM,
    STROKE_VOLTS,
    UNITS,
    ParameterModel,
    check_vector,
)
from .residuals import check_volts, loop_residuals, noise_directions, reference_points
from .simulate import NEAR_SINGULAR_MM

WIDE_MARGIN_FACTOR = 8.0
# Five times the paper's 40 mV: beyond this the residuals are not sensor noise.
MAX_NOISE_VOLTS = 0.2
# Relative gradient |G^T f| / (|G| |f|) that counts as zero when no step helps.
GTOL = 1e-6
MAX_LOOSE_PASSES = 4
MAX_PASSES = 6


@dataclass(frozen=True)
class Identification:
    """Result of :func:`identify`.

    Attributes
    ----------
    model : ParameterModel
        The free/tied/fixed split identified.
    params : ndarray, shape (20,)
        The full estimate (mm, mm/V); fixed parameters as in ``start``.
    start : ndarray, shape (20,)
        The start.
    std : ndarray, shape (n,)
        Predicted standard deviations of the free parameters, in the order of
        ``model.free`` (mm or mm/V).
    covariance : ndarray, shape (n, n)
        Their covariance.
    sigma_volts : float
        The per-channel voltage noise of one scan (1 sigma, V) the covariance assumes:
        given, or estimated from the residuals.
    sigma_estimated : bool
        True if ``sigma_volts`` was estimated, False if it was given.
    rms_residual : float
        RMS of the residuals at the solution: the loop residuals f in mm^2 (paper), the
        readings' misfit in V (ml, as if every pose were one scan).
    iterations : int
        Iterations of all passes together.
    converged : bool
        Whether the last pass converged.
    message : str
        How the last pass ended.
    used : ndarray of bool, shape (m,)
        The poses used.
    excluded : ndarray of int
        Indices of the near-singular or inconsistent poses left out.
    indices : ObservabilityIndices
        Observability indices of the used poses at the solution (ml: of the information
        rows, one per pose).
    history : list of float
        The objective after each accepted step (``f^T f`` in mm^4 for paper, the whitened
        misfit for ml), every pass's start included.
    method : str
        ``"ml"`` or ``"paper"``.
    rotations : ndarray, shape (m_used, 3, 3), or None
        The estimated plate rotations of the used poses (ml; None for paper).
    """

    model: ParameterModel
    params: np.ndarray
    start: np.ndarray
    std: np.ndarray
    covariance: np.ndarray
    sigma_volts: float
    sigma_estimated: bool
    rms_residual: float
    iterations: int
    converged: bool
    message: str
    used: np.ndarray
    excluded: np.ndarray
    indices: ObservabilityIndices
    history: list[float] = field(default_factory=list, repr=False)
    method: str = "paper"
    rotations: np.ndarray | None = field(default=None, repr=False)

    @property
    def free_values(self) -> np.ndarray:
        """The estimated free parameters, shape (n,), in the order of ``model.free``."""
        return self.model.free_values(self.params)

    def problems(
        self,
        *,
        max_noise_volts: float = MAX_NOISE_VOLTS,
        max_excluded: float = 0.2,
        max_condition: float = CONDITION_OK,
    ) -> list[str]:
        """Reasons not to trust the result.

        Parameters
        ----------
        max_noise_volts : float, default MAX_NOISE_VOLTS
            Largest believable ``sigma_volts``, V (0.2, five times the paper's 40 mV);
            beyond it the residuals are not sensor noise (a wrong model, a swapped or dead
            channel, a moving plate).
        max_excluded : float, default 0.2
            Largest fraction of the poses that may be excluded.
        max_condition : float, default CONDITION_OK
            Largest acceptable condition number of the used poses (1000).

        Returns
        -------
        list of str
            One sentence per problem (no convergence, too much noise, too many poses
            excluded, ill-conditioned); empty if none.
        """
        out = []
        if not self.converged:
            out.append(f"did not converge ({self.message})")
        if self.sigma_volts > max_noise_volts:
            out.append(
                f"residuals imply {1000 * self.sigma_volts:.0f} mV of sensor noise, more than "
                f"{1000 * max_noise_volts:.0f} mV: the readings do not fit the model"
            )
        n_all = len(self.used)
        if len(self.excluded) > max_excluded * n_all:
            out.append(f"{len(self.excluded)} of {n_all} poses were unusable (near-singular)")
        if self.indices.condition > max_condition:
            out.append(f"condition number {self.indices.condition:.3g} exceeds {max_condition:g}")
        return out

    def table(self, truth: np.ndarray | None = None) -> str:
        """A readable table of the free parameters: start, estimate, std (and truth, error).

        Parameters
        ----------
        truth : array_like, shape (20,), optional
            The true parameters (simulations): adds the columns truth, error and
            error / std.

        Returns
        -------
        str
            One line per free parameter and a last line with the iterations, the poses
            used, the residual, the noise and the indices.
        """
        head = f"{'param':>6} {'unit':>5} {'start':>10} {'estimate':>11} {'std':>8}"
        if truth is not None:
            head += f" {'truth':>10} {'error':>9} {'err/std':>7}"
        lines = [head]
        for j, name in enumerate(self.model.free):
            i = self.model.free_index[j]
            line = (
                f"{name:>6} {UNITS[name]:>5} {self.start[i]:10.4f} {self.params[i]:11.4f} "
                f"{self.std[j]:8.4f}"
            )
            if truth is not None:
                err = self.params[i] - truth[i]
                line += f" {truth[i]:10.4f} {err:+9.4f} {err / self.std[j]:+7.2f}"
            lines.append(line)
        ix = self.indices
        lines.append(
            f"{self.iterations} iterations, {self.message}; poses used {int(self.used.sum())}"
            f" (excluded {len(self.excluded)}); {self.method}: rms residual "
            f"{self.rms_residual:.4g} {'V' if self.method == 'ml' else 'mm^2'}; "
            f"noise {1000 * self.sigma_volts:.1f} mV"
            f" ({'estimated' if self.sigma_estimated else 'given'}); "
            f"s_min {ix.min_singular:.4g}, condition {ix.condition:.4g}"
        )
        return "\n".join(lines)


def check_stroke(volts: np.ndarray, stroke_volts: float = STROKE_VOLTS) -> None:
    """Raise :class:`InputError` if a reading lies outside the LVDT's +-10 V span.

    The design matches the span to the actuator's +-37.5 mm stroke (docs/model.md section
    10).

    Parameters
    ----------
    volts : ndarray, shape (m, 4)
        LVDT readings, V.
    stroke_volts : float, default STROKE_VOLTS
        Half the span, V (10).

    Raises
    ------
    InputError
        If any ``|volts|`` exceeds ``stroke_volts`` (the message names the first).
    """
    bad = np.abs(volts) > stroke_volts
    if bad.any():
        k, i = np.argwhere(bad)[0]
        raise InputError(
            f"{int(bad.sum())} readings lie outside the +-{stroke_volts:g} V span of the "
            f"actuator stroke (+-{STROKE_MM} mm; first: pose {k}, sensor {i + 1}, "
            f"{volts[k, i]:+.3f} V)"
        )


def identify(
    volts: np.ndarray,
    model: ParameterModel = PAPER7,
    start: np.ndarray = NOMINAL,
    *,
    method: str = DEFAULT_METHOD,
    noise_volts: float | None = None,
    scans_per_pose: np.ndarray | None = None,
    max_iter: int = 100,
    xtol: float = 1e-8,
    ftol: float = 1e-12,
    near_singular_mm: float = NEAR_SINGULAR_MM,
    max_change: float = 50.0,
) -> Identification:
    """Identify the free parameters of ``model`` from m poses of sensor readings.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        LVDT readings of quasi-static poses, V (for example
        :func:`~loopcal.calibration.poses.still_poses`), each within +-10 V.
    model : ParameterModel, default PAPER7
        Which parameters are free, tied and fixed.
    start : array_like, shape (20,), default NOMINAL
        Full parameter vector to start from (mm, mm/V); fixed parameters keep its values.
    method : {"ml", "paper"}, default "ml"
        ``"ml"``: maximum likelihood by the implicit loop method
        (:mod:`loopcal.calibration.implicit`: every pose's rotation is estimated too, the
        readings are fitted directly, weighted by their noise). ``"paper"``: the paper's
        closed-loop residuals (docs/model.md section 5).
    noise_volts : float, optional
        Known per-channel noise of one scan (1 sigma, V) for the covariance (ml also takes
        one per channel, shape (4,)); None estimates it from the residuals.
    scans_per_pose : array_like, shape (m,), optional
        Scans averaged into each pose, whose noise is then noise / sqrt(n). ml weights the
        poses by it; the paper's method ignores it.
    max_iter : int, default 100
        Iterations at most, per pass.
    xtol : float, default 1e-8
        (paper) Converged when no free parameter is estimated to be further than this (in
        its unit) from the limit, judged from the step and the observed convergence rate.
    ftol : float, default 1e-12
        (paper) Or when the relative decrease of ``f^T f`` falls below it near the
        Gauss-Newton regime (damping <= 1). ml ignores xtol and ftol: it stops when a step
        lowers the whitened misfit by less than
        :data:`loopcal.calibration.implicit.DECREMENT_TOL` of one residual's variance.
    near_singular_mm : float, default NEAR_SINGULAR_MM
        (paper) Poses whose mirror solutions come closer than this, mm (at the estimate),
        are excluded and reported. ml excludes the poses whose rotation the lengths do not
        determine (:data:`loopcal.calibration.implicit.MIN_POSE_SIGMA_MM`) instead.
    max_change : float, default 50.0
        A free parameter moving further than this from the start (in its unit) is
        divergence.

    Returns
    -------
    Identification
        The estimate with its covariance, residuals, the poses used and their indices.

    Raises
    ------
    InputError
        Bad readings (shape, NaN, outside +-10 V), an unknown method, fewer poses (or
        usable poses) than free parameters, or (ml) bad ``noise_volts`` or
        ``scans_per_pose``.
    ParameterError
        If ``start`` fails :func:`~loopcal.calibration.parameters.check_vector`.
    UnobservableError
        The free set is rank deficient on these poses.
    ConvergenceError
        Divergence: a free parameter reached ``max_change``.

    Notes
    -----
    The paper's method minimises ``f^T f`` by Levenberg-Marquardt on the column-scaled
    Jacobian ``g H``, ``H = diag(sqrt(M) / ||g_j||)`` (module docstring), in passes: the
    first keeps only the poses far from singular at the start (if enough are), later ones
    every pose usable at the estimate, until the set settles. The covariance is the
    sandwich estimate of the module docstring.
    """
    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    V = check_volts(volts)
    p0 = check_vector(start).copy()
    check_stroke(V)
    n = model.n_free
    m = V.shape[0]
    if m < n:
        raise InputError(f"{m} poses cannot identify {n} free parameters; record at least {n}")
    if method == "ml":
        return _identify_ml(V, model, p0, noise_volts, scans_per_pose, max_iter, max_change)

    def margins(p: np.ndarray, ref: np.ndarray) -> np.ndarray:
        """Smallest branch separation of each pose, mm (-1 where spheres miss)."""
        r = loop_residuals(p, V, ref, jacobian=False)
        return np.where(r.feasible.all(axis=1), r.separation.min(axis=1), -1.0)

    x0 = model.free_values(p0)
    p = p0
    # A start far from the truth misplaces the branch references by up to ~10 mm, so the
    # first pass keeps only poses whose mirror solutions lie far apart; the final pass uses
    # every pose that is usable at the estimate.
    ref = reference_points(V, p0)
    sep = margins(p0, ref)
    wide = sep >= WIDE_MARGIN_FACTOR * near_singular_mm
    used = wide if wide.sum() >= max(n, m // 4) else sep >= near_singular_mm
    history: list[float] = []
    total_iter = 0
    tight = False
    for attempt in range(MAX_PASSES):
        if used.sum() < n:
            raise InputError(
                f"only {int(used.sum())} of {m} poses are usable ({int((~used).sum())} "
                f"near-singular or inconsistent); {n} free parameters need at least {n}"
            )
        # Loose passes (the wide one, then all usable poses) bring the estimate, and with it
        # the branch references and the usable set, close; once the set has settled, a tight
        # pass converges on it (and again if that changes the set).
        p, f, g, it, converged, message = _levenberg_marquardt(
            V[used], ref[used], model, p, x0, p0, max_iter,
            xtol if tight else max(xtol, 1e-3), ftol if tight else max(ftol, 1e-4),
            max_change, history,
        )  # fmt: skip
        total_iter += it
        if attempt == MAX_PASSES - 1:
            break
        ref = reference_points(V, p)
        # hysteresis: a pose in the fit stays while it keeps 90 % of the margin
        sep = margins(p, ref)
        now = (sep >= near_singular_mm) | (used & (sep >= 0.9 * near_singular_mm))
        if now.sum() < n:  # keep the fitted set rather than drop below n poses
            if tight:
                break
            tight = True
            continue
        settled = attempt >= 1 and np.array_equal(now, used)
        if tight and settled:
            break
        tight = tight or settled or attempt >= MAX_LOOSE_PASSES - 1
        used = now
    excluded = np.flatnonzero(~used)
    cost = history[-1]
    it = total_iter
    _check_bound(model, p, p0, max_change)

    h = column_scales(g, model.free)
    G = g * h
    s = np.linalg.svd(G, compute_uv=False)
    u, sk, _ = noise_directions(p, V[used], ref[used])
    w = np.einsum("mi,mi->m", u, f.reshape(-1, 4)) / sk  # whitened: variance sigma_V^2 each
    mu = len(sk)
    if noise_volts is None:
        dof = max(mu - n, 1)
        sigma = float(np.sqrt(np.sum(w**2) / dof))
        estimated = True
    else:
        sigma = float(noise_volts)
        estimated = False
    Ginv = np.linalg.inv(G.T @ G)
    gk = G.reshape(mu, 4, n)
    # D_k D_k^T ~ s_k^2 u_k u_k^T: the meat of the sandwich is sum_k (g_k^T u_k s_k)^2.
    a = np.einsum("mrn,mr->mn", gk, u) * sk[:, None]
    meat = a.T @ a
    cov_s = sigma**2 * Ginv @ meat @ Ginv
    cov = cov_s * np.outer(h, h)
    std = np.sqrt(np.diag(cov))
    return Identification(
        model=model,
        params=p,
        start=p0,
        std=std,
        covariance=cov,
        sigma_volts=sigma,
        sigma_estimated=estimated,
        rms_residual=float(np.sqrt(cost / len(f))),
        iterations=it,
        converged=converged,
        message=message,
        used=used,
        excluded=excluded,
        indices=ObservabilityIndices(s, mu),
        history=history,
    )


def _check_bound(model: ParameterModel, p: np.ndarray, p0: np.ndarray, max_change: float):
    """Raise ConvergenceError if the fit ran into the bound on the change: whatever it
    settled on there is not a minimum."""
    at_bound = np.abs(model.free_values(p) - model.free_values(p0)) >= max_change * 0.999
    if at_bound.any():
        names = ", ".join(n for n, b in zip(model.free, at_bound, strict=True) if b)
        raise ConvergenceError(
            f"diverged: {names} moved more than {max_change} from the start; check the "
            "start values, the free set and the readings"
        )


def _identify_ml(V, model, p0, noise_volts, scans_per_pose, max_iter, max_change):
    """The "ml" branch of :func:`identify` (inputs already checked)."""
    n = model.n_free
    m = len(V)
    T = model.tie_matrix
    w = implicit.pose_weights(m, noise_volts, scans_per_pose)
    R, used = implicit.start_rotations(V, p0)
    history: list[float] = []
    p, total_iter = p0, 0
    Rfit, fitted = R, used
    for attempt in range(3):  # the usable set is judged again at the estimate
        if used.sum() < n:
            raise InputError(
                f"only {int(used.sum())} of {m} poses are usable ({int((~used).sum())} "
                f"near-singular or unsolvable); {n} free parameters need at least {n}"
            )
        at_start = implicit.linearise(V[used], w[used], R[used], p, T)
        require_observable(at_start.information()[:, None, :], model)
        p, Rfit, it, converged, message, at_fit = implicit.fit_linearised(
            V[used], w[used], R[used], T, p, max_iter=max_iter, max_change=max_change,
            history=history, at_start=at_start,
        )  # fmt: skip
        total_iter += it
        fitted = used
        _check_bound(model, p, p0, max_change)
        # forward kinematics at the estimate, started from the fitted rotations where the
        # fit has them (a few steps instead of a solution from scratch)
        R_now = np.empty_like(R)
        ok = np.zeros(m, dtype=bool)
        R_now[used], ok[used] = implicit.start_rotations(V[used], p, start=Rfit)
        if not used.all():
            R_now[~used], ok[~used] = implicit.start_rotations(V[~used], p)
        R_now[used] = Rfit  # the fitted rotations where the fit has them
        R = R_now
        if np.array_equal(ok, used) or attempt == 2:
            break
        used = ok
    used = fitted
    # the covariance at the solution, from the fit's last linearisation
    r = at_fit.r.T
    rows = at_fit.information()
    info = rows.T @ rows
    cost = at_fit.cost
    mu = int(used.sum())
    if noise_volts is None:
        # each pose leaves one degree of freedom (four readings, three angles)
        scale = float(np.sqrt(cost / max(mu - n, 1)))
        sigma, estimated = scale, True  # weights assumed 1 V: the scale is the noise
    else:
        scale, sigma, estimated = 1.0, float(np.mean(noise_volts)), False
    cov = scale**2 * np.linalg.inv(info)
    h = column_scales(rows[:, None, :], model.free)
    sv = np.linalg.svd(rows * h, compute_uv=False)
    misfit = r / implicit.pose_weights(1, noise_volts, None)  # V, as if one scan per pose
    return Identification(
        model=model,
        params=p,
        start=p0,
        std=np.sqrt(np.diag(cov)),
        covariance=cov,
        sigma_volts=sigma,
        sigma_estimated=estimated,
        rms_residual=float(np.sqrt(np.mean(misfit**2))),
        iterations=total_iter,
        converged=converged,
        message=message,
        used=used,
        excluded=np.flatnonzero(~used),
        indices=ObservabilityIndices(sv, mu),
        history=history,
        method="ml",
        rotations=Rfit,
    )


def _levenberg_marquardt(V, ref, model, p_start, x0, p0, max_iter, xtol, ftol, max_change, history):
    """LM with column scaling on poses V from p_start. The branch references ``ref`` (forward
    kinematics at p_start) stay fixed, so the objective is smooth within one call."""
    n = model.n_free
    T = model.tie_matrix

    def residuals(p: np.ndarray):
        r = loop_residuals(p, V, ref, jacobian=False)
        return r.residuals.reshape(-1), r

    def jacobian(r) -> np.ndarray:
        return r.derivative(T).reshape(-1, n)

    p = p_start
    f, r = residuals(p)
    g = jacobian(r)
    require_observable(g, model)
    x = model.free_values(p)
    cost = float(f @ f)
    history.append(cost)
    damping = Damping()
    prev_step = 0.0
    converged = False
    message = "maximum iterations reached"
    it = 0
    while it < max_iter:
        it += 1
        h = column_scales(g, model.free)
        G = g * h
        GtG = G.T @ G
        grad = G.T @ f
        diag = np.diag(np.diag(GtG))
        step_taken = False
        while not damping.exhausted:
            ds = np.linalg.solve(GtG + damping.lam * diag, -grad)
            x_new = x + h * ds
            f_new = None
            if np.all(np.abs(x_new - x0) <= max_change):
                p_new = model.expand(x_new, p0)
                f_new, r_new = residuals(p_new)
            if f_new is not None and np.isfinite(f_new).all():
                new_cost = float(f_new @ f_new)
                # gain ratio: actual over predicted reduction of f^T f (Nielsen's damping)
                predicted = float(ds @ (damping.lam * diag @ ds - grad))
                rho = (cost - new_cost) / predicted if predicted > 0 else -1.0
                if rho > 0:
                    damping.accept(rho)
                    step_taken = True
                    break
            damping.refuse()
        if not step_taken:
            # no step lowers f^T f: a minimum to rounding if the gradient vanishes there
            if np.linalg.norm(grad) <= GTOL * np.linalg.norm(G) * np.sqrt(cost):
                converged, message = True, "converged (gradient)"
            else:
                message = "no step reduces the residuals (stalled)"
            break
        # Gauss-Newton converges linearly on these large-residual problems: estimate the rate
        # from successive steps and stop when the remaining distance, about
        # step * rate / (1 - rate), is below xtol
        step = np.abs(x_new - x).max()
        rate = min(step / prev_step, 0.9) if prev_step > 0 else 0.9
        small_step = step * max(rate / (1.0 - rate), 1.0) <= xtol
        prev_step = step
        small_gain = cost - new_cost <= ftol * cost and damping.lam <= 1.0
        g_new = jacobian(r_new)
        if not np.isfinite(g_new).all():  # a pose hit a degenerate configuration
            damping.refuse()
            continue
        x, p, cost, f, g = x_new, p_new, new_cost, f_new, g_new
        history.append(cost)
        if small_step or small_gain or cost == 0.0:
            converged, message = True, "converged"
            break
    return p, f, g, it, converged, message
