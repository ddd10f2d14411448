"""Maximum-likelihood calibration by the implicit loop method (docs/model.md section 9).

Each pose k has an unknown plate rotation ``R_k`` besides the free parameters x. The model
predicts every reading from inverse kinematics,

    Vhat_ki = (|R_k Bh_i - A_i| - d0_i) / S_i          (V; Bh_i the plate point of leg i),

and the estimate minimises the whitened misfit ``sum_ki (V_ki - Vhat_ki)^2 / sigma_ki^2``
over x and all rotations, with ``sigma_ki = sigma_i / sqrt(n_k)`` for a still pose averaged
from n_k scans of channel noise sigma_i. With Gaussian noise this is the maximum-likelihood
estimate; the paper's squared-length loop residuals are not (they put the noise inside
squares, which biases the fit at O(sigma^2) and weighs the channels unequally).

Rotations are updated by left increments ``R <- exp([w]x) R`` (w in rad, base frame), as in
:func:`calibration.kinematics.forward_kinematics`. Per pose the whitened residual r_k (4,)
has the Jacobians ``Jp_k`` (4, n) and ``Jr_k`` (4, 3). The Gauss-Newton normal equations are
block-arrow sparse; eliminating each pose's 3x3 block (Schur complement)

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
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from .errors import InputError
from .kinematics import (
    LEG_POINT,
    base_points,
    check_rotations,
    forward_kinematics,
    home_derivative,
    plate_home,
    volts_to_lengths,
)
from .parameters import BASE_COORDS, I_K1, I_K2, I_K3, N_PARAMS, SL_GAIN, SL_OFFSET, check_vector

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
    """Readings (m, 4) in V that rotations R (m, 3, 3) produce with parameters p (20,)."""
    R = check_rotations(R)
    p = check_vector(p)
    B = np.einsum("mij,bj->mbi", R, plate_home(p))[:, LEG_POINT]
    dist = np.linalg.norm(B - base_points(p), axis=-1)
    return (dist - p[SL_OFFSET]) / p[SL_GAIN]


def model_jacobians(
    R: np.ndarray, p: np.ndarray, directions: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Predicted readings and their derivatives.

    R: (m, 3, 3) rotations; p: (20,); directions: (20, q) parameter directions (default the
    identity; a model's tie matrix gives derivatives with respect to its free values).
    Returns Vhat (m, 4) in V, dVhat/dp along ``directions`` (m, 4, q) and dVhat/dw (m, 4, 3)
    for left rotation increments w in rad.
    """
    Wd = np.eye(N_PARAMS) if directions is None else np.asarray(directions, dtype=float)
    home = plate_home(p)
    legs = list(LEG_POINT)
    B = np.einsum("mij,bj->mbi", R, home)[:, legs]  # (m, 4, 3)
    diff = B - base_points(p)
    dist = np.linalg.norm(diff, axis=-1)
    u = diff / dist[..., None]
    S = p[SL_GAIN]
    vhat = (dist - p[SL_OFFSET]) / S
    m = len(R)
    G = np.zeros((m, 4, N_PARAMS))
    for (pt, ax), ip in BASE_COORDS.items():
        G[:, pt, ip] = -u[:, pt, ax]
    dB = np.einsum("mij,kbj->mkbi", R, home_derivative(p))[:, :, legs]  # (m, 3, 4, 3)
    G[:, :, [I_K1, I_K2, I_K3]] = np.einsum("mli,mkli->mlk", u, dB)
    G /= S[:, None]
    idx = np.arange(4)
    G[:, idx, SL_GAIN.start + idx] = -vhat / S
    G[:, idx, SL_OFFSET.start + idx] = -1.0 / S
    Jr = np.cross(B, u) / S[:, None]
    return vhat, G @ Wd, Jr


def loop_direction(Jr: np.ndarray) -> np.ndarray:
    """q (m, 4): for each pose the unit vector orthogonal to the columns of its (whitened)
    rotation Jacobian Jr (m, 4, 3): the part of its readings no rotation explains. Its sign
    is arbitrary."""
    # the left singular vector of Jr_k for its zero singular value
    U, _, _ = np.linalg.svd(Jr, full_matrices=True)
    return U[:, :, 3]


def information_rows(Jp: np.ndarray, Jr: np.ndarray) -> np.ndarray:
    """Each pose's information about the parameters once its rotation is eliminated.

    Jp: (m, 4, n) and Jr: (m, 4, 3) Jacobians of whitened residuals. Returns a (m, n): the
    pose's information matrix is ``a_k a_k^T`` (rank one: four readings, three angles).
    """
    return np.einsum("mrn,mr->mn", Jp, loop_direction(Jr))


def weighted_information(
    R: np.ndarray, p: np.ndarray, directions: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """:func:`information_rows` (m, n) of poses at rotations R (m, 3, 3) and parameters p,
    along ``directions`` (20, n), with the readings whitened by ``weights`` (m, 4), 1/sigma."""
    _, Jp, Jr = model_jacobians(R, p, directions)
    return information_rows(Jp * weights[..., None], Jr * weights[..., None])


def pose_weights(
    m: int, noise_volts: float | np.ndarray | None, scans_per_pose: np.ndarray | None
) -> np.ndarray:
    """Whitening weights 1/sigma_ki, (m, 4): ``sqrt(n_k) / sigma_i`` (sigma 1 V if None)."""
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
    """The Cramér-Rao lower bound on the covariance of the free parameters (n, n).

    R: (m, 3, 3) the true rotations of the poses; p: (20,) the true parameters; directions:
    (20, n) the free directions (a model's ``tie_matrix``); noise_volts: per-channel noise of
    one scan (V, scalar or (4,)); scans_per_pose: (m,) scans averaged into each pose.
    No unbiased estimator from these readings can have a smaller covariance.
    """
    R = check_rotations(R)
    p = check_vector(p)
    a = weighted_information(R, p, directions, pose_weights(len(R), noise_volts, scans_per_pose))
    return np.linalg.inv(a.T @ a)


def start_rotations(volts: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (m, 3, 3) from forward kinematics of the readings at p, and (m,) whether
    each pose is usable (converged, away from singularities)."""
    fk = forward_kinematics(volts_to_lengths(volts, p), p)
    ok = fk.converged & (fk.sigma_min >= MIN_POSE_SIGMA_MM) & np.isfinite(fk.rms_mm)
    return fk.rotations, ok


def fit(
    volts: np.ndarray,
    weights: np.ndarray,
    R0: np.ndarray,
    directions: np.ndarray,
    p_start: np.ndarray,
    *,
    max_iter: int = 100,
    max_change: float = 50.0,
    history: list[float] | None = None,
) -> tuple[np.ndarray, np.ndarray, int, bool, str]:
    """Levenberg-Marquardt on parameters and rotations with the pose blocks eliminated.

    volts: (m, 4); weights: (m, 4) 1/sigma; R0: (m, 3, 3) start rotations; directions:
    (20, n) free directions; p_start: (20,) start (fixed parameters keep its values).
    Returns (params, rotations, iterations, converged, message).
    """
    history = [] if history is None else history
    n = directions.shape[1]
    p, R = p_start.copy(), R0.copy()

    def state(p, R):
        vhat, Jp, Jr = model_jacobians(R, p, directions)
        r = (volts - vhat) * weights
        return r, -Jp * weights[..., None], -Jr * weights[..., None]

    r, Jp, Jr = state(p, R)
    cost = float(np.sum(r * r))
    history.append(cost)
    lam, nu = 1e-3, 2.0
    converged, message, it = False, "maximum iterations reached", 0
    dof = max(len(volts) - n, 1)
    while it < max_iter:
        it += 1
        U = np.einsum("mri,mrj->ij", Jp, Jp)
        Wk = np.einsum("mri,mrj->mij", Jp, Jr)  # (m, n, 3)
        Vk = np.einsum("mri,mrj->mij", Jr, Jr)  # (m, 3, 3)
        gp = np.einsum("mri,mr->i", Jp, r)
        gk = np.einsum("mri,mr->mi", Jr, r)
        dU = np.diag(U).copy()
        dV = np.einsum("mii->mi", Vk).copy()
        step_taken = False
        first_predicted = None  # the decrease the least damped step of this turn predicts
        while lam < 1e12:
            Vd = Vk + lam * dV[:, :, None] * np.eye(3)
            try:
                Vinv = np.linalg.inv(Vd)
            except np.linalg.LinAlgError:
                lam *= nu
                nu *= 2.0
                continue
            WV = Wk @ Vinv  # (m, n, 3)
            Sc = U + np.diag(lam * dU) - np.einsum("mij,mkj->ik", WV, Wk)
            rhs = -(gp - np.einsum("mij,mj->i", WV, gk))
            try:
                dx = np.linalg.solve(Sc, rhs)
            except np.linalg.LinAlgError:
                lam *= nu
                nu *= 2.0
                continue
            dw = -np.einsum("mij,mj->mi", Vinv, gk + np.einsum("mij,i->mj", Wk, dx))
            p_new = p + directions @ dx
            ok = np.all(np.abs(p_new - p_start) <= max_change) and np.all(np.isfinite(dw))
            if ok:
                R_new = Rotation.from_rotvec(dw).as_matrix() @ R
                r_new, Jp_new, Jr_new = state(p_new, R_new)
                new_cost = float(np.sum(r_new * r_new))
                predicted = float(dx @ (lam * dU * dx - gp) + np.sum(dw * (lam * dV * dw - gk)))
                if first_predicted is None:
                    first_predicted = predicted
                    if predicted <= 10 * DECREMENT_TOL * max(cost / dof, EXACT_FIT):
                        break  # at the minimum to rounding: stop here, below
                rho = (cost - new_cost) / predicted if predicted > 0 else -1.0
                if np.isfinite(new_cost) and rho > 0:
                    lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                    nu = 2.0
                    step_taken = True
                    break
            lam *= nu
            nu *= 2.0
        if not step_taken:
            floor = DECREMENT_TOL * max(cost / dof, EXACT_FIT)
            if cost <= EXACT_FIT * r.size:
                converged, message = True, "converged (exact fit)"
            elif first_predicted is not None and first_predicted <= 10 * floor:
                # at the minimum to rounding: even the Gauss-Newton step promises less than
                # the tolerance, and rounding hides it
                converged, message = True, "converged (at rounding level)"
            else:
                message = "no step reduces the misfit (stalled)"
            break
        decrement = cost - new_cost
        p, R, r, Jp, Jr, cost = p_new, R_new, r_new, Jp_new, Jr_new, new_cost
        history.append(cost)
        # the decrement is in whitened units; compared with the misfit per degree of
        # freedom it is independent of the noise level assumed
        if decrement <= DECREMENT_TOL * max(cost / dof, EXACT_FIT) and lam <= 1.0:
            converged, message = True, "converged"
            break
    return p, R, it, converged, message
