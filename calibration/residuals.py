"""The paper's closed-loop residuals and their analytic Jacobian (MODEL.md section 5).

For pose k, loop i predicts sensor i's length from the other three and compares squares:
``f_i(k) = |B(k) - A_i|^2 - d_i(k)^2`` in mm^2, where the plate point B comes from two chained
three-sphere intersections that do not use sensor i. The residual vector of m poses is
``f.reshape(4 m)``, pose-major, i.e. the paper's ``f(4k - 3 .. 4k)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .kinematics import D_BASE, base_points, forward_kinematics, plate_points, volts_to_lengths
from .parameters import I_K1, I_K2, I_K3, N_PARAMS, SL_GAIN, SL_OFFSET, check_vector
from .spheres import SphereIntersection, intersect_three_spheres

_E = np.eye(N_PARAMS)


@dataclass(frozen=True)
class LoopResiduals:
    """residuals: (m, 4) in mm^2; jacobian: (m, 4, 20) derivative with respect to the full
    parameter vector, or None; separation: (m, 4) the smaller branch separation of the two
    intersections in each loop, mm; feasible: (m, 4) False where a sphere triple has no real
    intersection (inconsistent readings)."""

    residuals: np.ndarray
    jacobian: np.ndarray | None
    separation: np.ndarray
    feasible: np.ndarray


def check_volts(volts: np.ndarray) -> np.ndarray:
    """Validate sensor voltages: shape (m, 4), finite. Returns a float array."""
    V = np.asarray(volts, dtype=float)
    if V.ndim == 1 and V.shape == (4,):
        V = V[None]
    if V.ndim != 2 or V.shape[1] != 4:
        raise InputError(f"sensor voltages must have shape (m, 4), got {V.shape}")
    bad = ~np.isfinite(V)
    if bad.any():
        k, i = np.argwhere(bad)[0]
        raise InputError(
            f"sensor voltages contain {bad.sum()} NaN or infinite values "
            f"(first: pose {k}, sensor {i + 1})"
        )
    return V


def reference_points(volts: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Plate points B1, B2 (m, 2, 3) from forward kinematics with parameters ``p``.

    They select the assembly branch of each intersection in :func:`loop_residuals`.
    """
    V = check_volts(volts)
    fk = forward_kinematics(volts_to_lengths(V, p), p)
    return plate_points(fk.rotations, p)


def loop_residuals(
    p: np.ndarray,
    volts: np.ndarray,
    ref: np.ndarray,
    *,
    jacobian: bool = True,
    directions: np.ndarray | None = None,
) -> LoopResiduals:
    """Closed-loop residuals of m poses, optionally with their analytic Jacobian.

    p: full parameter vector (20,); volts: (m, 4) sensor voltages in V; ref: (m, 2, 3) reference
    plate points (see :func:`reference_points`) that pick the branch of every intersection.
    directions: (20, q) parameter directions to differentiate along (default: the identity,
    giving ``df/dp``); pass a model's tie matrix to get ``df/dx`` at a fraction of the cost.
    """
    p = check_vector(p)
    V = check_volts(volts)
    m = V.shape[0]
    A = base_points(p)
    d = volts_to_lengths(V, p)
    W = _E if directions is None else np.asarray(directions, dtype=float)
    if jacobian:
        # forward-mode seeds along W: d(d_i)/dW, d(A)/dW
        dd = V[:, :, None] * W[SL_GAIN] + W[SL_OFFSET]
        dA = D_BASE @ W

    def sphere(k: int, i: int, second: tuple, which: int) -> SphereIntersection:
        """sphere(O, p[k]) & sphere(A_i, d_i) & second = (centre, d centre, radius, d radius)."""
        P2, dP2, r2, dr2 = second
        if not jacobian:
            return intersect_three_spheres(p[k], A[i], d[:, i], P2, r2, ref[:, which])
        return intersect_three_spheres(
            p[k], A[i], d[:, i], P2, r2, ref[:, which],
            d_r0=W[k], d_P1=dA[i], d_r1=dd[:, i], d_P2=dP2, d_r2=dr2,
        )  # fmt: skip

    def base(i: int) -> tuple:
        return (A[i], dA[i], d[:, i], dd[:, i]) if jacobian else (A[i], None, d[:, i], None)

    def plate(b: SphereIntersection) -> tuple:
        return (b.point, b.jacobian, p[I_K3], W[I_K3] if jacobian else None)

    # B2 from sensors 3, 4 and B1 from sensors 1, 2 are each shared by two loops.
    b2_34 = sphere(I_K2, 2, base(3), 1)
    b1_12 = sphere(I_K1, 0, base(1), 0)
    loops = (  # (first intersection, second intersection, the sensor left out)
        (b2_34, sphere(I_K1, 1, plate(b2_34), 0), 0),
        (b2_34, sphere(I_K1, 0, plate(b2_34), 0), 1),
        (b1_12, sphere(I_K2, 3, plate(b1_12), 1), 2),
        (b1_12, sphere(I_K2, 2, plate(b1_12), 1), 3),
    )
    f = np.empty((m, 4))
    sep = np.empty((m, 4))
    feas = np.empty((m, 4), dtype=bool)
    J = np.empty((m, 4, W.shape[1])) if jacobian else None
    for i, (first, second, target) in enumerate(loops):
        e = second.point - A[target]
        f[:, i] = np.einsum("mi,mi->m", e, e) - d[:, target] ** 2
        sep[:, i] = np.minimum(first.separation, second.separation)
        feas[:, i] = first.feasible & second.feasible
        if jacobian:
            de = second.jacobian - dA[target]
            J[:, i] = 2.0 * (e[:, None, :] @ de)[:, 0] - 2.0 * d[:, target, None] * dd[:, target]
    return LoopResiduals(f, J, sep, feas)


def noise_sensitivity(
    p: np.ndarray, volts: np.ndarray, ref: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """How each pose's residuals respond to noise on its own readings.

    ``D_k = df_k / dV_k`` (4 x 4, mm^2/V) is nearly rank one: the four residuals of a pose
    measure one loop-closure error. Returns its leading singular pair, u (m, 4) and s (m,) in
    mm^2/V, so that voltage noise e_k moves the residuals by about ``u_k s_k (v_k . e_k)``.
    """
    offsets = np.eye(N_PARAMS)[:, SL_OFFSET]  # d f / d d0 = d f / d d(k) of each pose
    D = loop_residuals(p, volts, ref, directions=offsets).jacobian * p[SL_GAIN]
    U, sv, _ = np.linalg.svd(D)
    return U[:, :, 0], sv[:, 0]
