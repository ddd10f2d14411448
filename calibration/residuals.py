"""The paper's closed-loop residuals and their analytic Jacobian (docs/model.md section 5).

For pose k, loop i predicts sensor i's length from the other three and compares squares:
``f_i(k) = |B(k) - A_i|^2 - d_i(k)^2`` in mm^2, where the plate point B comes from two chained
three-sphere intersections that do not use sensor i. The residual vector of m poses is
``f.reshape(4 m)``, pose-major, i.e. the paper's ``f(4k - 3 .. 4k)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import InputError
from .kinematics import base_points, forward_kinematics, plate_points, volts_to_lengths
from .parameters import (
    BASE_COORDS,
    I_K1,
    I_K2,
    I_K3,
    N_PARAMS,
    SL_GAIN,
    SL_OFFSET,
    check_vector,
)
from .smallmat import dot3
from .spheres import adjoint, solve

_E = np.eye(N_PARAMS)


@dataclass(frozen=True)
class LoopResiduals:
    """Closed-loop residuals of m poses (result of :func:`loop_residuals`).

    Attributes
    ----------
    residuals : ndarray, shape (m, 4)
        ``f_i(k)``, mm^2 (see :func:`loop_residuals`).
    jacobian : ndarray, shape (m, 4, q), or None
        Derivative with respect to the parameters along the ``directions`` asked for
        (q = 20, the full vector, by default); None if not asked for.
    separation : ndarray, shape (m, 4)
        The smaller branch separation of the two intersections in each loop, mm (small:
        near a singular configuration).
    feasible : ndarray of bool, shape (m, 4)
        False where a sphere triple has no real intersection (inconsistent readings).
    """

    residuals: np.ndarray
    jacobian: np.ndarray | None
    separation: np.ndarray
    feasible: np.ndarray
    _state: tuple | None = field(default=None, repr=False, compare=False)

    def derivative(self, directions: np.ndarray | None = None) -> np.ndarray:
        """The Jacobian along ``directions``, from the intersections already solved.

        Only the reverse sweep runs, so an accepted trial step costs no second forward
        solve. Needs a result of :func:`loop_residuals` (it keeps the intersections).

        Parameters
        ----------
        directions : array_like, shape (20, q), optional
            Parameter directions to differentiate along; default the identity (all 20
            parameters). A model's ``tie_matrix`` gives derivatives with respect to its
            free values.

        Returns
        -------
        ndarray, shape (m, 4, q)
            ``df/dp @ directions``, mm^2 per unit of each direction.
        """
        W = _E if directions is None else np.asarray(directions, dtype=float)
        return _jacobian(self._state, W)


def check_volts(volts: np.ndarray) -> np.ndarray:
    """Validate sensor voltages: shape (m, 4), finite.

    Parameters
    ----------
    volts : array_like, shape (m, 4) or (4,)
        LVDT readings, V.

    Returns
    -------
    ndarray, shape (m, 4)
        ``volts`` as a float array, one reading of shape (4,) promoted to (1, 4). The range
        is not checked (:func:`loopcal.calibration.identify.check_stroke` does).

    Raises
    ------
    InputError
        If the shape is wrong or a value is NaN or infinite (the message names the first).
    """
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
    """Plate points B1, B2 from forward kinematics with parameters ``p``.

    They select the assembly branch of each intersection in :func:`loop_residuals`. Four
    Gauss-Newton steps place the plate to well under a millimetre, far inside the separation
    of the branches.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        LVDT readings, V.
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V).

    Returns
    -------
    ndarray, shape (m, 2, 3)
        B1 and B2 in the base frame, mm.

    Raises
    ------
    InputError
        If ``volts`` fails :func:`check_volts`.
    ParameterError, numpy.linalg.LinAlgError
        As :func:`~loopcal.calibration.kinematics.forward_kinematics`.
    """
    V = check_volts(volts)
    p = check_vector(p)  # before its gains and offsets are used
    # a few Gauss-Newton steps place the plate to well under a millimetre, far inside the
    # separation of the branches the references choose between
    fk = forward_kinematics(volts_to_lengths(V, p), p, max_iter=4)
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

    Parameters
    ----------
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V).
    volts : array_like, shape (m, 4)
        LVDT readings, V.
    ref : array_like, shape (m, 2, 3)
        Reference plate points B1, B2, mm (:func:`reference_points`), that pick the branch
        of every intersection.
    jacobian : bool, default True
        Also compute the Jacobian.
    directions : array_like, shape (20, q), optional
        Parameter directions to differentiate along; default the identity, giving
        ``df/dp``. Pass a model's tie matrix to get ``df/dx`` at a fraction of the cost.

    Returns
    -------
    LoopResiduals
        Residuals (m, 4) in mm^2, the Jacobian (m, 4, q) or None, branch separations and
        feasibility.

    Raises
    ------
    ParameterError
        If ``p`` fails :func:`~loopcal.calibration.parameters.check_vector`.
    InputError
        If ``volts`` fails :func:`check_volts`.

    Notes
    -----
    Loop i leaves sensor i out. With lengths ``d = S V + d0``, the plate point shared by the
    other two sensors' actuators comes from one three-sphere intersection (B2 from (O, k2),
    (A3, d3), (A4, d4) for loops 1 and 2; B1 from (O, k1), (A1, d1), (A2, d2) for loops 3
    and 4), the other plate point from a second one through the remaining sensor and
    ``|B1 B2| = k3``; the residual compares the predicted and the measured squared length
    of the sensor left out::

        f_i(k) = |B(k) - A_i|^2 - d_i(k)^2        (mm^2)

    The derivatives come from implicit differentiation of the sphere equations, in reverse
    mode (:func:`loopcal.calibration.spheres.adjoint`). Where a sphere triple does not meet,
    the closest approach keeps the residual continuous and ``feasible`` is False.
    """
    p = check_vector(p)
    V = check_volts(volts)
    m = V.shape[0]
    A = base_points(p)[:, :, None]  # (4, 3, 1): component-major, like everything below
    VT = np.ascontiguousarray(V.T)  # (4, m)
    d = VT * p[SL_GAIN, None] + p[SL_OFFSET, None]  # (4, m) lengths, d = S V + d0
    refs = np.ascontiguousarray(np.transpose(np.asarray(ref, dtype=float), (1, 2, 0)))
    k3 = p[I_K3]
    # B2 from sensors 3, 4 and B1 from sensors 1, 2 are each shared by two loops.
    b2 = solve(p[I_K2], A[2], d[2], A[3], d[3], refs[1])
    b1 = solve(p[I_K1], A[0], d[0], A[1], d[1], refs[0])
    loops = (
        # (first, its (k, sensor, sensor)), second, its (k, sensor), the sensor left out
        (b2, (I_K2, 2, 3), solve(p[I_K1], A[1], d[1], b2.x, k3, refs[0]), (I_K1, 1), 0),
        (b2, (I_K2, 2, 3), solve(p[I_K1], A[0], d[0], b2.x, k3, refs[0]), (I_K1, 0), 1),
        (b1, (I_K1, 0, 1), solve(p[I_K2], A[3], d[3], b1.x, k3, refs[1]), (I_K2, 3), 2),
        (b1, (I_K1, 0, 1), solve(p[I_K2], A[2], d[2], b1.x, k3, refs[1]), (I_K2, 2), 3),
    )
    f = np.empty((4, m))
    sep = np.empty((4, m))
    feas = np.empty((4, m), dtype=bool)
    errors = []
    for i, (first, _, second, _, t) in enumerate(loops):
        e = second.x - A[t]
        errors.append(e)
        f[i] = dot3(e, e) - d[t] ** 2
        sep[i] = np.minimum(first.separation, second.separation)
        feas[i] = first.feasible & second.feasible
    state = (loops, errors, A, d, VT, m)
    out = LoopResiduals(f.T, None, sep.T, feas.T, state)
    if jacobian:
        out = replace(out, jacobian=out.derivative(directions))
    return out


def _jacobian(state: tuple, W: np.ndarray) -> np.ndarray:
    """Reverse sweep over the four loops: (m, 4, q) derivatives along W (20, q)."""
    loops, errors, A, d, VT, m = state
    J = np.empty((4, W.shape[1], m))
    for i, ((first, (kf, j, l), second, (ks, s_i), t), e) in enumerate(
        zip(loops, errors, strict=True)
    ):
        # the gradient of f_i with respect to all 20 parameters, per pose
        grad_d = np.zeros((4, m))  # d f / d d_s (lengths)
        grad_A = np.zeros((4, 3, m))  # d f / d A_s
        G = np.zeros((N_PARAMS, m))
        g2 = 2.0 * e
        a0, a1, a2, bA, bx = adjoint(second, g2)
        G[ks] += a0
        G[I_K3] += a2
        grad_d[s_i] += a1
        grad_A[s_i] += bA
        a0, a1, a2, bA1, bA2 = adjoint(first, bx)  # through the shared plate point
        G[kf] += a0
        grad_d[j] += a1
        grad_d[l] += a2
        grad_A[j] += bA1
        grad_A[l] += bA2
        grad_A[t] -= g2
        grad_d[t] -= 2.0 * d[t]
        G[SL_GAIN] += grad_d * VT  # d = S V + d0
        G[SL_OFFSET] += grad_d
        for (pt, ax), ip in BASE_COORDS.items():
            G[ip] += grad_A[pt, ax]
        J[i] = W.T @ G
    return np.transpose(J, (2, 0, 1))


def noise_directions(
    p: np.ndarray, volts: np.ndarray, ref: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The leading singular triple of ``D_k = df_k / dV_k`` for each pose: how its residuals
    respond to noise on its own readings.

    ``D_k`` (4 x 4, mm^2/V) is nearly rank one: the four residuals of a pose measure one
    loop-closure error. Voltage noise e_k moves the residuals by about
    ``u_k s_k (v_k . e_k)``, and a pose's whitened loop-closure error ``u_k . f_k / s_k``
    has variance ``sum_i v_ki^2 sigma_i^2`` for channel noises sigma_i.

    Parameters
    ----------
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), as in :func:`loop_residuals`.
    volts : array_like, shape (m, 4)
        LVDT readings, V, as in :func:`loop_residuals`.
    ref : array_like, shape (m, 2, 3)
        Reference plate points, mm, as in :func:`loop_residuals`.

    Returns
    -------
    u : ndarray, shape (m, 4)
        Leading left singular vectors.
    s : ndarray, shape (m,)
        Leading singular values, mm^2/V.
    v : ndarray, shape (m, 4)
        Leading right singular vectors: the mix of the four channels' noise that opens the
        loop.
    """
    offsets = np.eye(N_PARAMS)[:, SL_OFFSET]  # d f / d d0 = d f / d d(k) of each pose
    D = loop_residuals(p, volts, ref, directions=offsets).jacobian * p[SL_GAIN]
    U, sv, Vt = np.linalg.svd(D)
    return U[:, :, 0], sv[:, 0], Vt[:, 0, :]
