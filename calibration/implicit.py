"""Maximum-likelihood calibration by the implicit loop method (docs/model.md section 9).

Each pose k has an unknown plate rotation ``R_k`` besides the free parameters x. The model
predicts every reading from inverse kinematics::

    Vhat_ki = (|R_k Bh_i - A_i| - d0_i) / S_i          (V; Bh_i the plate point of leg i),

and the estimate minimises the whitened misfit ``sum_ki (V_ki - Vhat_ki)^2 / sigma_ki^2``
over x and all rotations, with ``sigma_ki = sigma_i / sqrt(n_k)`` for a still pose averaged
from n_k scans of channel noise sigma_i. With Gaussian noise this is the maximum-likelihood
estimate; the paper's squared-length loop residuals are not (they put the noise inside
squares, which biases the fit at O(sigma^2) and weighs the channels unequally).

Rotations are updated by left increments ``R <- exp([w]x) R`` (w in rad, base frame), as in
:func:`loopcal.calibration.kinematics.forward_kinematics`. Per pose the whitened residual r_k (4,)
has the Jacobians ``Jp_k`` (4, n) and ``Jr_k`` (4, 3). The Gauss-Newton normal equations are
block-arrow sparse; eliminating each pose's 3x3 block (Schur complement)::

    (U - sum_k W_k V_k^-1 W_k^T) dx = -(g_p - sum_k W_k V_k^-1 g_k),
    dw_k = -V_k^-1 (g_k + W_k^T dx),

with ``U = sum Jp_k^T Jp_k``, ``W_k = Jp_k^T Jr_k``, ``V_k = Jr_k^T Jr_k``, ``g_p = sum
Jp_k^T r_k``, ``g_k = Jr_k^T r_k``, makes one iteration cost O(m n^2): linear in the number
of poses. Levenberg-Marquardt damping scales the diagonals of U and every V_k.

Information. Four readings fix three rotation angles, so once the rotation is eliminated a
pose tells one number about the parameters: its information is ``a_k a_k^T`` with
``a_k = Jp_k^T q_k`` and q_k the unit vector orthogonal to the columns of ``Jr_k``. The
Cramér-Rao bound of a pose set is ``(sum_k a_k a_k^T)^-1`` (whitened units), and pose
selection on the rows a_k is a rank-one design problem.

Implementation. Inside, arrays are component-major (the pose index last: residuals (4, m),
rotation Jacobians (3, 4, m), rotations (3, 3, m)) and every 3x3 operation is in closed form
(:mod:`loopcal.calibration.smallmat`), so each one is a handful of elementwise operations over
contiguous pose arrays. The parameter Jacobian is kept as its nonzero entries only: a
parameter moves one leg (a base coordinate, a gain, an offset), two (k2, k3) or four (k1),
so row i of ``Jp_k`` is ``sum_l g_lk T[param_l]`` over the pairs l = (param_l, leg_l = i)
of a free direction's parameter and a leg it moves (K pairs, :class:`_Pairs`);
``sum_k Jp_k^T Jp_k``, ``W_k`` and the information rows then cost O(m K) plus one small
matrix product each. The damped pose blocks are eliminated through their Cholesky factors,
``V_k = L_k L_k^T``, ``Z_k = W_k L_k^-T``: the Schur complement is ``U - sum_k Z_k Z_k^T``
(one product of (n, 3m) matrices) and ``dw_k = -L_k^-T (L_k^-1 g_k + Z_k^T dx)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .damping import Damping
from .errors import InputError
from .kinematics import (
    LEG_POINT,
    base_points,
    check_rotations,
    forward_kinematics,
    home_derivative,
    leg_vectors,
    plate_home,
    volts_to_lengths,
)
from .parameters import BASE_COORDS, I_K1, I_K2, I_K3, N_PARAMS, SL_GAIN, SL_OFFSET, check_vector
from .smallmat import (
    cholesky3,
    cross3,
    gram3,
    matmul3,
    matvec3,
    null_vector_4x3,
    rotvec_to_matrix,
)

#: a pose whose forward-kinematics Jacobian has a smallest singular value below this (mm per
#: rad of rotation) is near a singularity: its rotation is not determined by its lengths
MIN_POSE_SIGMA_MM = 2.0
#: converged when the Gauss-Newton step moves the misfit by less than this fraction of the
#: noise (in units of one whitened residual's variance): every parameter is then within a
#: small fraction of its standard deviation of the minimum
DECREMENT_TOL = 1e-8
#: whitened misfit per reading at which readings count as fitted exactly (noise-free data):
#: 1e-10 V RMS at the default unit weights
EXACT_FIT = 1e-20


def predicted_volts(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The readings that plate rotations produce with given parameters (no noise).

    Parameters
    ----------
    R : array_like, shape (m, 3, 3)
        Plate rotations.
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V).

    Returns
    -------
    ndarray, shape (m, 4)
        ``Vhat = (|R Bh_i - A_i| - d0_i) / S_i``, V (not quantised, not clipped).

    Raises
    ------
    InputError
        If ``R`` fails :func:`~loopcal.calibration.kinematics.check_rotations`.
    ParameterError
        If ``p`` fails :func:`~loopcal.calibration.parameters.check_vector`.
    """
    R = check_rotations(R)
    p = check_vector(p)
    B = np.einsum("mij,bj->mbi", R, plate_home(p))[:, LEG_POINT]
    dist = np.linalg.norm(B - base_points(p), axis=-1)
    return (dist - p[SL_OFFSET]) / p[SL_GAIN]


#: parameter index -> (base point, axis) of the base coordinates
_BASE_COORD_OF = {ip: pt_ax for pt_ax, ip in BASE_COORDS.items()}


def _legs_moved(i: int) -> tuple[int, ...]:
    """The legs (0..3) whose predicted reading parameter i (0..19) changes."""
    if i in _BASE_COORD_OF:  # A_pt moves leg pt only
        return (_BASE_COORD_OF[i][0],)
    if i == I_K1:  # B1 = k1 u1, and B2's position in the plane depends on k1 too
        return (0, 1, 2, 3)
    if i in (I_K2, I_K3):  # B2 only
        return (2, 3)
    if SL_GAIN.start <= i < SL_GAIN.stop:
        return (i - SL_GAIN.start,)
    return (i - SL_OFFSET.start,)  # an offset


class _Pairs:
    """The nonzero entries of the parameter Jacobian along directions T (20, n).

    The K pairs l = (parameter ``param[l]``, leg ``leg[l]``) for which the parameter has a
    nonzero direction and moves that leg. With ``g_lk`` the derivative of leg ``leg[l]``'s
    reading of pose k with respect to parameter ``param[l]``, the Jacobian along T is
    ``Jp_k[i] = sum_{l: leg[l] = i} g_lk T[param[l]]``; ``Tl`` (K, n) holds those rows of T.
    """

    def __init__(self, directions: np.ndarray | None):
        T = np.eye(N_PARAMS) if directions is None else np.asarray(directions, dtype=float)
        pairs = [(i, leg) for i in np.flatnonzero(np.any(T != 0, axis=1)) for leg in _legs_moved(i)]
        self.n = T.shape[1]
        self.param = np.array([i for i, _ in pairs], dtype=int)
        self.leg = np.array([leg for _, leg in pairs], dtype=int)
        self.Tl = T[self.param]  # (K, n)
        self.same_leg = self.leg[:, None] == self.leg[None, :]
        self.k_derivative = bool(np.isin(self.param, (I_K1, I_K2, I_K3)).any())

    def expand(self, G: np.ndarray) -> np.ndarray:
        """The Jacobian (n, 4, m) along T from the pair entries G (K, m)."""
        out = np.zeros((self.n, 4, G.shape[1]))
        for i in range(4):
            sel = self.leg == i
            if sel.any():
                out[:, i] = self.Tl[sel].T @ G[sel]
        return out

    def contract(self, G: np.ndarray, x: np.ndarray) -> np.ndarray:
        """``sum_i Jp_k[i] x_ik`` (n, m) for x (4, m): Jp_k^T x_k for every pose at once."""
        return self.Tl.T @ (G * x[self.leg])


def _derivatives(Rc: np.ndarray, p: np.ndarray, pairs: _Pairs, f: np.ndarray):
    """Predicted readings and their derivatives, component-major, with each leg's
    derivatives multiplied by ``f * S_i`` (f (4, m) or (4, 1)).

    Rc: (3, 3, m) rotations; p: (20,). Returns vhat (4, m) in V, ``f S dvhat/dw`` (3, 4, m)
    (w in rad, left increments) and the pair entries ``f S dvhat/dp`` (K, m) of
    :class:`_Pairs`. ``f = 1 / S`` gives the plain derivatives; ``f = -weights / S`` those of
    the whitened residuals ``(V - vhat) weights``.
    """
    home = plate_home(p)
    B, u, dist = leg_vectors(Rc, home, base_points(p))
    S = p[SL_GAIN][:, None]
    vhat = (dist - p[SL_OFFSET][:, None]) / S
    Jr = cross3(B, u) * f
    RdB = None
    if pairs.k_derivative:  # dB/dk rotated into the base frame, (3 k, 2 points, 3, m)
        dB = home_derivative(p)
        RdB = [[matvec3(Rc, v) for v in dk] for dk in dB]
    m = Rc.shape[-1]
    G = np.empty((len(pairs.param), m))
    for row, (i, leg) in enumerate(zip(pairs.param, pairs.leg, strict=True)):
        if i in _BASE_COORD_OF:  # d|B - A| / dA = -u
            G[row] = -u[_BASE_COORD_OF[i][1], leg] * f[leg]
        elif i in (I_K1, I_K2, I_K3):
            v = RdB[i - I_K1][LEG_POINT[leg]]
            G[row] = (u[0, leg] * v[0] + u[1, leg] * v[1] + u[2, leg] * v[2]) * f[leg]
        elif SL_GAIN.start <= i < SL_GAIN.stop:
            G[row] = -vhat[leg] * f[leg]
        else:  # an offset
            G[row] = -f[leg]
    return vhat, Jr, G


def _cm(R: np.ndarray) -> np.ndarray:
    """Rotations (m, 3, 3) as a component-major (3, 3, m) array."""
    return np.ascontiguousarray(np.moveaxis(R, 0, -1))


def _pm(Rc: np.ndarray) -> np.ndarray:
    """Component-major rotations (3, 3, m) as a pose-major (m, 3, 3) array."""
    return np.ascontiguousarray(np.moveaxis(Rc, -1, 0))


def model_jacobians(
    R: np.ndarray, p: np.ndarray, directions: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted readings and their derivatives.

    Parameters
    ----------
    R : ndarray, shape (m, 3, 3)
        Plate rotations; not validated.
    p : ndarray, shape (20,)
        Full parameter vector (mm, mm/V); not validated.
    directions : array_like, shape (20, q), optional
        Parameter directions; default the identity. A model's tie matrix gives derivatives
        with respect to its free values.

    Returns
    -------
    vhat : ndarray, shape (m, 4)
        Predicted readings, V.
    Jp : ndarray, shape (m, 4, q)
        dVhat/dp along ``directions``, V per unit of each direction.
    Jr : ndarray, shape (m, 4, 3)
        dVhat/dw for left rotation increments ``R <- exp([w]x) R``, V/rad.
    """
    pairs = _Pairs(directions)
    vhat, Jr, G = _derivatives(_cm(R), p, pairs, 1.0 / p[SL_GAIN][:, None])
    Jp = np.ascontiguousarray(pairs.expand(G).transpose(2, 1, 0))
    return np.ascontiguousarray(vhat.T), Jp, np.ascontiguousarray(Jr.transpose(2, 1, 0))


def _loop_direction(Jr: np.ndarray) -> np.ndarray:
    """:func:`loop_direction` component-major: Jr (3, 4, m) -> q (4, m)."""
    q = null_vector_4x3(Jr)
    bad = ~np.isfinite(q).all(axis=0)
    if bad.any():  # dependent columns (an exact singularity): the SVD picks a direction
        J = np.moveaxis(Jr[:, :, bad], -1, 0).transpose(0, 2, 1)  # (b, 4, 3)
        q[:, bad] = np.linalg.svd(J, full_matrices=True)[0][:, :, 3].T
    return q


def loop_direction(Jr: np.ndarray) -> np.ndarray:
    """For each pose, the unit vector orthogonal to the columns of its rotation Jacobian:
    the part of its readings no rotation explains.

    Parameters
    ----------
    Jr : array_like, shape (m, 4, 3)
        (Whitened) rotation Jacobians, one per pose.

    Returns
    -------
    ndarray, shape (m, 4)
        q, unit vectors; the sign is arbitrary.

    Notes
    -----
    In closed form, the generalised cross product of the three columns (the left singular
    vector of Jr_k for its zero singular value, without an SVD per pose); where the columns
    are linearly dependent (no unique direction) it falls back to the SVD's choice.
    """
    return _loop_direction(np.moveaxis(np.asarray(Jr, dtype=float), 0, -1).transpose(1, 0, 2)).T


def weighted_information(
    R: np.ndarray, p: np.ndarray, directions: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """The information rows a_k of poses: pose k's information about the parameters once
    its rotation is eliminated is ``a_k a_k^T`` (module docstring).

    Parameters
    ----------
    R : ndarray, shape (m, 3, 3)
        Plate rotations, as in :func:`model_jacobians`.
    p : ndarray, shape (20,)
        Full parameter vector (mm, mm/V), as in :func:`model_jacobians`.
    directions : array_like, shape (20, n)
        Free directions (a model's ``tie_matrix``).
    weights : array_like, shape (m, 4)
        Whitening of the readings, 1/sigma in 1/V (:func:`pose_weights`).

    Returns
    -------
    ndarray, shape (m, n)
        ``a_k = Jp_k^T q_k`` (whitened: per unit noise), with q_k from
        :func:`loop_direction` (its sign arbitrary).
    """
    pairs = _Pairs(directions)
    f = np.asarray(weights, dtype=float).T / p[SL_GAIN][:, None]
    _, Jr, G = _derivatives(_cm(R), p, pairs, f)
    return pairs.contract(G, _loop_direction(Jr)).T


def pose_weights(
    m: int, noise_volts: float | np.ndarray | None, scans_per_pose: np.ndarray | None
) -> np.ndarray:
    """Whitening weights 1/sigma_ki of m poses: ``sqrt(n_k) / sigma_i``.

    Parameters
    ----------
    m : int
        Number of poses.
    noise_volts : float or array_like, shape (4,), or None
        Per-channel noise of one scan sigma_i, V; None takes 1 V (unit weights, the noise
        then estimated from the misfit).
    scans_per_pose : array_like, shape (m,), or None
        Scans n_k averaged into each pose; None takes 1.

    Returns
    -------
    ndarray, shape (m, 4)
        Weights, 1/V.

    Raises
    ------
    InputError
        If a noise is not positive and finite, or ``scans_per_pose`` is not m positive
        finite counts.
    """
    sigma = (
        np.ones(4)
        if noise_volts is None
        else np.broadcast_to(np.asarray(noise_volts, dtype=float), (4,))
    )
    if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
        raise InputError(f"noise_volts must be positive, got {noise_volts!r}")
    n = np.ones(m) if scans_per_pose is None else np.asarray(scans_per_pose, dtype=float)
    if n.shape != (m,) or not np.all(np.isfinite(n)) or np.any(n <= 0):
        raise InputError(f"scans_per_pose must be {m} positive counts, one per pose")
    return np.sqrt(n)[:, None] / sigma[None, :]


def cramer_rao(
    R: np.ndarray,
    p: np.ndarray,
    directions: np.ndarray,
    *,
    noise_volts: float | np.ndarray,
    scans_per_pose: np.ndarray | None = None,
) -> np.ndarray:
    """The Cramér-Rao lower bound on the covariance of the free parameters.

    No unbiased estimator from these readings can have a smaller covariance.

    Parameters
    ----------
    R : array_like, shape (m, 3, 3)
        The true rotations of the poses.
    p : array_like, shape (20,)
        The true parameters (mm, mm/V).
    directions : array_like, shape (20, n)
        The free directions (a model's ``tie_matrix``).
    noise_volts : float or array_like, shape (4,)
        Per-channel noise of one scan, 1 sigma, V.
    scans_per_pose : array_like, shape (m,), optional
        Scans averaged into each pose; default one each.

    Returns
    -------
    ndarray, shape (n, n)
        ``(sum_k a_k a_k^T)^-1``, in the free parameters' units squared.

    Raises
    ------
    InputError
        Bad rotations, noise or scan counts.
    ParameterError
        If ``p`` fails :func:`~loopcal.calibration.parameters.check_vector`.
    numpy.linalg.LinAlgError
        If the information matrix is singular (the free set is not observable).
    """
    R = check_rotations(R)
    p = check_vector(p)
    a = weighted_information(R, p, directions, pose_weights(len(R), noise_volts, scans_per_pose))
    return np.linalg.inv(a.T @ a)


def start_rotations(
    volts: np.ndarray, p: np.ndarray, *, start: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Plate rotations from forward kinematics of the readings, and which poses are usable.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        LVDT readings, V, as in :func:`~loopcal.calibration.kinematics.volts_to_lengths`.
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), as in
        :func:`~loopcal.calibration.kinematics.forward_kinematics`.
    start : array_like, shape (m, 3, 3), optional
        Rotations near the answer to start forward kinematics from (for example the fitted
        ones, when judging the poses again at the estimate); by default it starts from the
        sphere intersections.

    Returns
    -------
    rotations : ndarray, shape (m, 3, 3)
        From :func:`~loopcal.calibration.kinematics.forward_kinematics`.
    usable : ndarray of bool, shape (m,)
        Converged, finite, and with ``sigma_min`` at least :data:`MIN_POSE_SIGMA_MM`
        (away from singularities).

    Raises
    ------
    InputError, ParameterError, numpy.linalg.LinAlgError
        As :func:`~loopcal.calibration.kinematics.forward_kinematics`.
    """
    p = check_vector(p)  # before its gains and offsets are used
    fk = forward_kinematics(volts_to_lengths(volts, p), p, start=start)
    ok = fk.converged & (fk.sigma_min >= MIN_POSE_SIGMA_MM) & np.isfinite(fk.rms_mm)
    return fk.rotations, ok


@dataclass(frozen=True)
class Linearised:
    """The whitened residuals of m poses and their derivatives at one point (p, R),
    component-major (pose index last).

    Attributes
    ----------
    r : ndarray, shape (4, m)
        Whitened residuals ``(V - Vhat) * weights``.
    Jr : ndarray, shape (3, 4, m)
        dr/dw, w in rad (left increments).
    G : ndarray, shape (K, m)
        The nonzero entries of dr/dp, one row per (parameter, leg) pair of ``pairs``.
    pairs : _Pairs
        Which parameter and leg each row of G belongs to, and the free directions.
    cost : float
        ``sum r^2``, the whitened misfit.
    """

    r: np.ndarray
    Jr: np.ndarray
    G: np.ndarray
    pairs: _Pairs
    cost: float

    def information(self) -> np.ndarray:
        """The information rows a_k at this point (as :func:`weighted_information`).

        Returns
        -------
        ndarray, shape (m, n)
        """
        return self.pairs.contract(self.G, _loop_direction(self.Jr)).T


def _evaluate(
    Rc: np.ndarray, p: np.ndarray, Vc: np.ndarray, wc: np.ndarray, pairs: _Pairs
) -> Linearised:
    """One model evaluation: readings Vc (4, m) and weights wc (4, m) at rotations Rc
    (3, 3, m) and parameters p."""
    vhat, Jr, G = _derivatives(Rc, p, pairs, -wc / p[SL_GAIN][:, None])
    r = (Vc - vhat) * wc
    return Linearised(r, Jr, G, pairs, float(np.einsum("im,im->", r, r)))


def linearise(
    volts: np.ndarray, weights: np.ndarray, R: np.ndarray, p: np.ndarray, directions: np.ndarray
) -> Linearised:
    """The whitened problem linearised at rotations R and parameters p.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        LVDT readings, V.
    weights : array_like, shape (m, 4)
        1/sigma of each reading, 1/V (:func:`pose_weights`).
    R : ndarray, shape (m, 3, 3)
        Plate rotations.
    p : ndarray, shape (20,)
        Full parameter vector (mm, mm/V); not validated.
    directions : array_like, shape (20, n)
        Free directions (a model's ``tie_matrix``).

    Returns
    -------
    Linearised
    """
    Vc = np.ascontiguousarray(np.asarray(volts, dtype=float).T)
    wc = np.ascontiguousarray(np.asarray(weights, dtype=float).T)
    return _evaluate(_cm(R), p, Vc, wc, _Pairs(directions))


def fit_linearised(
    volts: np.ndarray,
    weights: np.ndarray,
    R0: np.ndarray,
    directions: np.ndarray,
    p_start: np.ndarray,
    *,
    max_iter: int = 100,
    max_change: float = 50.0,
    history: list[float] | None = None,
    at_start: Linearised | None = None,
) -> tuple[np.ndarray, np.ndarray, int, bool, str, Linearised]:
    """Levenberg-Marquardt on parameters and rotations with the pose blocks eliminated.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        LVDT readings, V.
    weights : array_like, shape (m, 4)
        1/sigma of each reading, 1/V.
    R0 : ndarray, shape (m, 3, 3)
        Start rotations.
    directions : ndarray, shape (20, n)
        Free directions (a model's ``tie_matrix``).
    p_start : ndarray, shape (20,)
        Start (fixed parameters keep its values); not validated.
    max_iter : int, default 100
        Iterations at most.
    max_change : float, default 50.0
        Steps that move any parameter further than this from ``p_start`` (in its unit) are
        refused; reaching it raises nothing here.
    history : list of float, optional
        Appended with the whitened misfit at the start and after each accepted step.
    at_start : Linearised, optional
        The problem linearised at (p_start, R0) if already at hand (for example from an
        observability check before the fit).

    Returns
    -------
    params : ndarray, shape (20,)
        The estimate.
    rotations : ndarray, shape (m, 3, 3)
        The fitted rotations.
    iterations : int
    converged : bool
    message : str
        How the iteration ended.
    linearised : Linearised
        The problem at the solution (for the covariance).
    """
    history = [] if history is None else history
    Vc = np.ascontiguousarray(np.asarray(volts, dtype=float).T)  # (4, m)
    wc = np.ascontiguousarray(np.asarray(weights, dtype=float).T)
    pairs = at_start.pairs if at_start is not None else _Pairs(directions)
    n = pairs.n
    p, Rc = p_start.copy(), _cm(R0)
    lin = at_start if at_start is not None else _evaluate(Rc, p, Vc, wc, pairs)
    cost = lin.cost
    history.append(cost)
    damping = Damping()
    converged, message, it = False, "maximum iterations reached", 0
    dof = max(Vc.shape[1] - n, 1)
    while it < max_iter:
        it += 1
        U, gp, W, V, gk = _normal_equations(lin)
        dU = np.diag(U).copy()
        dV = np.array(V[:3])  # (3, m) the pose blocks' diagonals
        step_taken = False
        first_predicted = None  # the decrease the least damped step of this turn predicts
        while not damping.exhausted:
            step = _damped_step(U, gp, W, V, gk, damping.lam)
            if step is None:  # a damped block not positive definite, or a singular system
                damping.refuse()
                continue
            dx, dw = step
            p_new = p + directions @ dx
            ok = np.all(np.abs(p_new - p_start) <= max_change) and np.all(np.isfinite(dw))
            if ok:
                Rc_new = matmul3(rotvec_to_matrix(dw), Rc)
                lin_new = _evaluate(Rc_new, p_new, Vc, wc, pairs)
                new_cost = lin_new.cost
                lam = damping.lam
                predicted = float(dx @ (lam * dU * dx - gp) + np.sum(dw * (lam * dV * dw - gk)))
                if first_predicted is None:
                    first_predicted = predicted
                    if predicted <= 10 * DECREMENT_TOL * max(cost / dof, EXACT_FIT):
                        break  # at the minimum to rounding: stop here, below
                rho = (cost - new_cost) / predicted if predicted > 0 else -1.0
                if np.isfinite(new_cost) and rho > 0:
                    damping.accept(rho)
                    step_taken = True
                    break
            damping.refuse()
        if not step_taken:
            floor = DECREMENT_TOL * max(cost / dof, EXACT_FIT)
            if cost <= EXACT_FIT * lin.r.size:
                converged, message = True, "converged (exact fit)"
            elif first_predicted is not None and first_predicted <= 10 * floor:
                # at the minimum to rounding: even the Gauss-Newton step promises less than
                # the tolerance, and rounding hides it
                converged, message = True, "converged (at rounding level)"
            else:
                message = "no step reduces the misfit (stalled)"
            break
        decrement = cost - new_cost
        p, Rc, lin, cost = p_new, Rc_new, lin_new, new_cost
        history.append(cost)
        # the decrement is in whitened units; compared with the misfit per degree of
        # freedom it is independent of the noise level assumed
        if decrement <= DECREMENT_TOL * max(cost / dof, EXACT_FIT) and damping.lam <= 1.0:
            converged, message = True, "converged"
            break
    return p, _pm(Rc), it, converged, message, lin


def _normal_equations(lin: Linearised):
    """The blocks of the Gauss-Newton normal equations at ``lin``.

    Returns U (n, n) = sum_k Jp_k^T Jp_k; gp (n,) = sum_k Jp_k^T r_k; W (n, 3, m) the
    ``Jp_k^T Jr_k``; V, the six distinct entries (v00, v11, v22, v01, v02, v12) of the
    ``Jr_k^T Jr_k``, each (m,); gk (3, m) the ``Jr_k^T r_k``.
    """
    pairs, G, Jr, r = lin.pairs, lin.G, lin.Jr, lin.r
    Tl = pairs.Tl
    U = Tl.T @ ((G @ G.T) * pairs.same_leg) @ Tl
    gp = Tl.T @ np.einsum("km,km->k", G, r[pairs.leg])
    K, m = G.shape
    H = G[:, None, :] * Jr[:, pairs.leg].transpose(1, 0, 2)  # (K, 3, m)
    W = (Tl.T @ H.reshape(K, 3 * m)).reshape(-1, 3, m)
    V = gram3(Jr)
    gk = np.einsum("aim,im->am", Jr, r)
    return U, gp, W, V, gk


def _damped_step(U, gp, W, V, gk, lam: float):
    """The Levenberg-Marquardt step (dx (n,), dw (3, m)) with damping lam on the diagonals
    of U and every pose block, the pose blocks eliminated through their Cholesky factors
    (module docstring); None if a damped block is not positive definite or the reduced
    system is singular."""
    v00, v11, v22, v01, v02, v12 = V
    d = 1.0 + lam
    l00, l10, l11, l20, l21, l22 = cholesky3(v00 * d, v11 * d, v22 * d, v01, v02, v12)
    if not (np.all(np.isfinite(l22)) and np.all(l00 > 0) and np.all(l11 > 0) and np.all(l22 > 0)):
        return None
    i00, i11, i22 = 1.0 / l00, 1.0 / l11, 1.0 / l22
    # Z = W L^-T, row by row (forward substitution), and h = L^-1 gk
    n, m = W.shape[0], W.shape[2]
    Z = np.empty((n, 3, m))
    z0, z1, z2 = Z[:, 0], Z[:, 1], Z[:, 2]
    np.multiply(W[:, 0], i00, out=z0)
    np.multiply(W[:, 1] - l10 * z0, i11, out=z1)
    np.multiply(W[:, 2] - l20 * z0 - l21 * z1, i22, out=z2)
    h = np.empty((3, m))
    np.multiply(gk[0], i00, out=h[0])
    np.multiply(gk[1] - l10 * h[0], i11, out=h[1])
    np.multiply(gk[2] - l20 * h[0] - l21 * h[1], i22, out=h[2])
    Z, h = Z.reshape(n, 3 * m), h.reshape(3 * m)
    Sc = U + np.diag(lam * np.diag(U)) - Z @ Z.T
    try:
        dx = np.linalg.solve(Sc, -(gp - Z @ h))
    except np.linalg.LinAlgError:
        return None
    # dw = -L^-T (h + Z^T dx), by back substitution
    t = h + dx @ Z
    t0, t1, t2 = t[:m], t[m : 2 * m], t[2 * m :]
    y2 = t2 * i22
    y1 = (t1 - l21 * y2) * i11
    y0 = (t0 - l10 * y1 - l20 * y2) * i00
    return dx, -np.stack([y0, y1, y2])


@dataclass(frozen=True)
class ScoreTest:
    """Result of :func:`score_test`.

    Attributes
    ----------
    statistic : float
        ``g^T C^-1 g``: how far the whitened misfit would fall if the extra directions were
        freed too (one Gauss-Newton step), in units of one reading's noise variance;
        chi-square with ``dof`` degrees of freedom when they are right.
    dof : int
        The number of extra directions.
    change : ndarray, shape (k,)
        The change of each extra direction that step would make (its unit).
    std : ndarray, shape (k,)
        Their standard deviations if they were freed (same units).
    """

    statistic: float
    dof: int
    change: np.ndarray
    std: np.ndarray


def score_test(
    volts: np.ndarray,
    weights: np.ndarray,
    R: np.ndarray,
    p: np.ndarray,
    directions: np.ndarray,
    extra: np.ndarray,
) -> ScoreTest:
    """Would parameters held fixed have fitted better if freed? The score (Lagrange
    multiplier) test at a fitted point.

    Parameters
    ----------
    volts, weights : array_like, shape (m, 4)
        Readings, V, and their whitening 1/sigma, 1/V (:func:`pose_weights`; with unit
        weights the statistic is in V^2 and must be divided by the noise variance).
    R : ndarray, shape (m, 3, 3)
        The fitted rotations.
    p : ndarray, shape (20,)
        The fitted parameters.
    directions : ndarray, shape (20, n)
        The fitted free directions (a model's ``tie_matrix``).
    extra : ndarray, shape (20, k)
        The directions to test (for example unit vectors of the gains S1..S4).

    Returns
    -------
    ScoreTest

    Notes
    -----
    With the rotations eliminated (module docstring), the information rows a_k over the
    free and extra directions give ``M = sum a_k a_k^T`` and the gradient ``g = sum a_k
    s_k`` (s_k the whitened misfit along pose k's loop direction). With the free directions
    eliminated, ``C = M_ee - M_ef M_ff^-1 M_fe`` is the extra directions' information and
    ``g_e - M_ef M_ff^-1 g_f`` their score. A wrong fixed parameter leaves a misfit that
    correlates with its information rows; the test is the most powerful one against exactly
    that alternative, and an error of about 4 of the ``std`` it reports fails it at the
    0.1 % level.
    """
    D = np.hstack([np.asarray(directions, dtype=float), np.asarray(extra, dtype=float)])
    n = np.asarray(directions).shape[1]
    lin = linearise(volts, weights, R, p, D)
    q = _loop_direction(lin.Jr)
    a = lin.pairs.contract(lin.G, q).T  # (m, n + k)
    s = np.einsum("im,im->m", q, lin.r)
    M, g = a.T @ a, a.T @ s
    Mff, Mfe, Mee = M[:n, :n], M[:n, n:], M[n:, n:]
    X = np.linalg.solve(Mff, np.column_stack([Mfe, g[:n]]))
    C = Mee - Mfe.T @ X[:, :-1]
    ge = g[n:] - Mfe.T @ X[:, -1]
    change = -np.linalg.solve(C, ge)
    std = np.sqrt(np.diag(np.linalg.inv(C)))
    return ScoreTest(float(-ge @ change), extra.shape[1], change, std)
