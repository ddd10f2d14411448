"""Inverse and forward kinematics of the shoulder joint, vectorised over poses.

Conventions: rotations are arrays of shape ``(m, 3, 3)`` mapping plate (home) coordinates to
base coordinates; lengths are ``(m, 4)`` in mm, ordered actuator 1..4. Actuators 1, 2 join A1,
A2 to the plate point B1; actuators 3, 4 join A3, A4 to B2 (docs/model.md sections 1, 4).
Z-Y-Z Euler angles are intrinsic, ``R = Rz(alpha) @ Ry(beta) @ Rz(gamma)``, in radians.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .errors import InputError, ParameterError
from .parameters import (
    B1_AZIMUTH_DEG,
    B2_AZIMUTH_DEG,
    B_ELEVATION_DEG,
    BASE_COORDS,
    I_K1,
    I_K2,
    I_K3,
    NAMES,
    SL_GAIN,
    SL_OFFSET,
    STROKE_MM,
    STROKE_VOLTS,
    UNITS,
    check_vector,
)
from .smallmat import cross3, eigmin_sym3, gram3, matmul3, matvec3, rotvec_to_matrix, solve_sym3
from .spheres import solve as solve_spheres

LEG_POINT = (0, 0, 1, 1)  #: actuator i ends at B1 (0) or B2 (1)


def _unit(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


_U1 = _unit(B1_AZIMUTH_DEG, B_ELEVATION_DEG)
_W = _unit(B2_AZIMUTH_DEG, B_ELEVATION_DEG)
_W = _W - (_W @ _U1) * _U1
_W /= np.linalg.norm(_W)


def base_points(p: np.ndarray) -> np.ndarray:
    """A1..A4, the base ends of the actuators, from a full parameter vector.

    Parameters
    ----------
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), in the order of
        :data:`~loopcal.calibration.parameters.NAMES`. Not validated.

    Returns
    -------
    ndarray, shape (4, 3)
        A1..A4 in the base frame, mm; the coordinates the frame fixes (A1y, A1z, A2z) are
        zero.
    """
    A = np.zeros((4, 3))
    for (pt, ax), ip in BASE_COORDS.items():
        A[pt, ax] = p[ip]
    return A


def plate_home(p: np.ndarray) -> np.ndarray:
    """B1 and B2, the plate ends of the actuators, at the identity rotation.

    B1 lies at azimuth 57.4 deg, elevation 45 deg, radius k1; B2 at radius k2 in the plane of
    B1 and the reference B2 direction (azimuth 237.4 deg, elevation 45 deg), at the angle that
    makes ``|B1 B2| = k3`` (90 deg for the reference design).

    Parameters
    ----------
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), in the order of
        :data:`~loopcal.calibration.parameters.NAMES`. Only k1, k2, k3 are used; not validated.

    Returns
    -------
    ndarray, shape (2, 3)
        B1 and B2 (home positions ``Bh``) in the plate frame, which is the base frame at the
        identity rotation, mm.
    """
    k1, k2, k3 = p[I_K1], p[I_K2], p[I_K3]
    cos_phi = (k1 * k1 + k2 * k2 - k3 * k3) / (2 * k1 * k2)
    phi = np.arccos(np.clip(cos_phi, -1.0, 1.0))
    return np.stack([k1 * _U1, k2 * (np.cos(phi) * _U1 + np.sin(phi) * _W)])


def home_derivative(p: np.ndarray) -> np.ndarray:
    """dBh/dk: the derivatives of the plate points at home with respect to k1, k2, k3.

    ``B1h = k1 u1``; ``B2h = a u1 + b w`` with ``a = (k1^2 + k2^2 - k3^2) / (2 k1)`` and
    ``b = sqrt(k2^2 - a^2)`` (see :func:`loopcal.calibration.kinematics.plate_home`).

    Parameters
    ----------
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), as in :func:`plate_home`.

    Returns
    -------
    ndarray, shape (3, 2, 3)
        ``out[k, b]`` the derivative of point b (B1, B2) with respect to k1, k2 or k3 (k),
        mm per mm. B1 depends on k1 only.
    """
    k1, k2, k3 = p[I_K1], p[I_K2], p[I_K3]
    a = (k1 * k1 + k2 * k2 - k3 * k3) / (2 * k1)
    b = np.sqrt(max(k2 * k2 - a * a, 1e-300))
    da = np.array([0.5 - (k2 * k2 - k3 * k3) / (2 * k1 * k1), k2 / k1, -k3 / k1])
    db = (np.array([0.0, k2, 0.0]) - a * da) / b
    out = np.zeros((3, 2, 3))
    out[0, 0] = _U1
    out[:, 1] = da[:, None] * _U1 + db[:, None] * _W
    return out


def lengths_to_volts(lengths: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Sensor voltages ``V = (d - d0) / S`` of actuator lengths.

    Parameters
    ----------
    lengths : array_like, shape (m, 4)
        Actuator lengths d, mm, actuators 1..4 (any shape ending in 4 broadcasts).
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), in the order of
        :data:`~loopcal.calibration.parameters.NAMES`. Only the gains S and offsets d0 are
        used; not validated.

    Returns
    -------
    ndarray, shape (m, 4)
        Voltages, V. Lengths outside the stroke give voltages beyond +-10 V: nothing is
        clipped.
    """
    return (np.asarray(lengths, dtype=float) - p[SL_OFFSET]) / p[SL_GAIN]


def volts_to_lengths(volts: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Actuator lengths ``d = S V + d0`` of sensor voltages.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        LVDT readings V, V, sensors 1..4 (any shape ending in 4 broadcasts).
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), as in :func:`lengths_to_volts`.

    Returns
    -------
    ndarray, shape (m, 4)
        Actuator lengths, mm.
    """
    return np.asarray(volts, dtype=float) * p[SL_GAIN] + p[SL_OFFSET]


def check_rotations(R: np.ndarray) -> np.ndarray:
    """Validate rotations: shape (m, 3, 3) (or (3, 3), promoted), finite, orthonormal.

    Parameters
    ----------
    R : array_like, shape (m, 3, 3) or (3, 3)
        Rotation matrices.

    Returns
    -------
    ndarray, shape (m, 3, 3)
        ``R`` as a float array, one (3, 3) promoted to shape (1, 3, 3).

    Raises
    ------
    InputError
        If the shape is wrong, an entry is not finite, or ``max |R R^T - I|`` exceeds 1e-6.
        (A reflection, determinant -1, passes.)
    """
    R = np.asarray(R, dtype=float)
    if R.shape == (3, 3):
        R = R[None]
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise InputError(f"rotations must have shape (m, 3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise InputError("rotations contain NaN or infinity")
    err = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(initial=0.0)
    if err > 1e-6:
        raise InputError(f"rotations are not orthonormal (max |R R^T - I| = {err:.2e})")
    return R


def plate_points(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """B1 and B2 in the base frame for each rotation.

    Parameters
    ----------
    R : ndarray, shape (m, 3, 3)
        Plate rotations; not validated.
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), in the order of
        :data:`~loopcal.calibration.parameters.NAMES`.

    Returns
    -------
    ndarray, shape (m, 2, 3)
        ``R @ Bh`` for B1 and B2 (:func:`plate_home`), mm.
    """
    return np.einsum("mij,bj->mbi", R, plate_home(p))


def inverse_kinematics(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Actuator lengths for plate rotations.

    Parameters
    ----------
    R : array_like, shape (m, 3, 3) or (3, 3)
        Plate rotations (plate home frame to base frame).
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), in the order of
        :data:`~loopcal.calibration.parameters.NAMES`.

    Returns
    -------
    ndarray, shape (m, 4)
        Lengths, mm: ``d1 = |R B1h - A1|``, ``d2 = |R B1h - A2|``, ``d3 = |R B2h - A3|``,
        ``d4 = |R B2h - A4|``. Not checked against the stroke (:func:`in_stroke`).

    Raises
    ------
    InputError
        If ``R`` fails :func:`check_rotations`.
    ParameterError
        If ``p`` fails :func:`~loopcal.calibration.parameters.check_vector`.
    """
    R = check_rotations(R)
    p = check_vector(p)
    B = plate_points(R, p)[:, LEG_POINT, :]  # (m, 4, 3)
    return np.linalg.norm(B - base_points(p), axis=-1)


def euler_zyz(R: np.ndarray) -> np.ndarray:
    """Intrinsic Z-Y-Z Euler angles (alpha, beta, gamma) of rotations.

    ``R = Rz(alpha) @ Ry(beta) @ Rz(gamma)`` (scipy's ``as_euler("ZYZ")``).

    Parameters
    ----------
    R : array_like, shape (m, 3, 3) or (3, 3)
        Rotations.

    Returns
    -------
    ndarray, shape (m, 3)
        (alpha, beta, gamma), rad. At zero tilt only alpha + gamma is defined; gamma is
        then reported as zero (scipy's gimbal-lock warning is silenced).

    Raises
    ------
    InputError
        If ``R`` fails :func:`check_rotations`.
    """
    from scipy.spatial.transform import Rotation  # scipy.spatial costs 0.1 s to import

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Gimbal lock")
        return Rotation.from_matrix(check_rotations(R)).as_euler("ZYZ")


def from_euler_zyz(angles: np.ndarray) -> np.ndarray:
    """Rotations from intrinsic Z-Y-Z Euler angles, the inverse of :func:`euler_zyz`.

    Parameters
    ----------
    angles : array_like, shape (m, 3) or (3,)
        (alpha, beta, gamma), rad.

    Returns
    -------
    ndarray, shape (m, 3, 3)
        ``Rz(alpha) @ Ry(beta) @ Rz(gamma)``; one angle triple gives shape (1, 3, 3).
    """
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("ZYZ", np.atleast_2d(angles)).as_matrix()


def tilt_swivel(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tilt of the output axis from +z and swivel about it (alpha + gamma).

    Parameters
    ----------
    R : array_like, shape (m, 3, 3) or (3, 3)
        Rotations, as in :func:`euler_zyz`.

    Returns
    -------
    tilt : ndarray, shape (m,)
        beta of :func:`euler_zyz`, rad, in [0, pi].
    swivel : ndarray, shape (m,)
        alpha + gamma, rad, wrapped to (-pi, pi].

    Raises
    ------
    InputError
        If ``R`` fails :func:`check_rotations`.
    """
    a, b, g = euler_zyz(R).T
    swivel = np.angle(np.exp(1j * (a + g)))
    return b, swivel


def output_axis_angles(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plate's output axis (its +z) for each rotation: how far and which way it leans.

    Parameters
    ----------
    R : array_like, shape (m, 3, 3)
        Rotations; not validated.

    Returns
    -------
    tilt : ndarray, shape (m,)
        Angle of the output axis from the base's +z, rad, in [0, pi].
    azimuth : ndarray, shape (m,)
        Direction it leans, rad, from +x towards +y, in [-pi, pi].
    """
    axis = np.asarray(R)[:, :, 2]
    tilt = np.arccos(np.clip(axis[:, 2], -1.0, 1.0))
    return tilt, np.arctan2(axis[:, 1], axis[:, 0])


@dataclass(frozen=True)
class ForwardSolution:
    """Result of :func:`forward_kinematics`.

    Attributes
    ----------
    rotations : ndarray, shape (m, 3, 3)
        Plate rotations fitting the four lengths in the least-squares sense (for a pose
        that did not converge, the last iterate).
    rms_mm : ndarray, shape (m,)
        RMS length misfit, mm (the loop-closure inconsistency of the reading).
    sigma_min : ndarray, shape (m,)
        Smallest singular value of the 4x3 length-to-rotation Jacobian, mm/rad (near zero:
        the orientation is poorly determined by the lengths).
    converged : ndarray of bool, shape (m,)
        Whether Gauss-Newton's step fell below ``sqrt(tol)`` within ``max_iter``.
    """

    rotations: np.ndarray
    rms_mm: np.ndarray
    sigma_min: np.ndarray
    converged: np.ndarray


def forward_kinematics(
    lengths: np.ndarray,
    p: np.ndarray,
    *,
    max_iter: int = 30,
    tol: float = 1e-12,
    start: np.ndarray | None = None,
) -> ForwardSolution:
    """Plate rotations from four actuator lengths (numerical forward kinematics).

    Parameters
    ----------
    lengths : array_like, shape (m, 4) or (4,)
        Actuator lengths, mm (for example :func:`volts_to_lengths` of the readings).
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), in the order of
        :data:`~loopcal.calibration.parameters.NAMES`.
    max_iter : int, default 30
        Gauss-Newton iterations at most.
    tol : float, default 1e-12
        A pose has converged once its rotation step is below ``sqrt(tol)`` rad.
    start : array_like, shape (m, 3, 3), optional
        Rotations to start Gauss-Newton from instead of the sphere intersections, for
        example the solution at nearby parameters (it then needs two or three steps instead
        of five to seven).

    Returns
    -------
    ForwardSolution
        Rotations, misfit, conditioning and convergence of each pose.

    Raises
    ------
    InputError
        If ``lengths`` is not (m, 4) or not finite, or ``start`` fails
        :func:`check_rotations` or does not hold m rotations.
    ParameterError
        If ``p`` fails :func:`~loopcal.calibration.parameters.check_vector`.
    numpy.linalg.LinAlgError
        Where the result is not finite (parameters such as A1x = 1e300, which describe no
        mechanism).

    Notes
    -----
    The start comes from two three-sphere intersections, B1 from (O, k1), (A1, d1), (A2, d2)
    and B2 from (O, k2), (A3, d3), (A4, d4), each on the assembly branch above the base
    (z > 0), by the rotation that carries the home frame of (B1, B2) onto theirs.
    Gauss-Newton on the rotation (left increments ``R <- exp([w]x) R``) then fits all four
    lengths in the least-squares sense.
    """
    d = np.atleast_2d(np.asarray(lengths, dtype=float))
    if d.ndim != 2 or d.shape[1] != 4:
        raise InputError(f"lengths must have shape (m, 4), got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise InputError("lengths contain NaN or infinity")
    p = check_vector(p)
    A = base_points(p)
    home = plate_home(p)
    m = d.shape[0]
    # component-major inside (pose index last): every operation runs over contiguous pose
    # arrays, and the 3x3 algebra is in closed form (loopcal.calibration.smallmat)
    dc = np.ascontiguousarray(d.T)  # (4, m)
    if start is None:
        up = np.array([[0.0], [0.0], [1.0]])
        b1 = solve_spheres(p[I_K1], A[0][:, None], dc[0], A[1][:, None], dc[1], up).x
        b2 = solve_spheres(p[I_K2], A[2][:, None], dc[2], A[3][:, None], dc[3], up).x
        Fh = _frame(home[0][:, None], home[1][:, None])  # (3, 3, 1)
        R = matmul3(_frame(b1, b2), Fh.transpose(1, 0, 2))
    else:
        R = check_rotations(start)
        if len(R) != m:
            raise InputError(f"start must hold {m} rotations, got {len(R)}")
        R = np.moveaxis(R, 0, -1).copy()  # (3, 3, m), a copy: it is updated in place
    converged = np.zeros(m, dtype=bool)
    active = np.arange(m)
    Ra, da = R, dc
    for _ in range(max_iter):
        J, dist = _length_jacobian(Ra, home, A)
        e = dist - da
        step = -solve_sym3(*gram3(J), np.einsum("aim,im->am", J, e))
        Ra = matmul3(rotvec_to_matrix(step), Ra)
        done = np.sqrt(np.einsum("am,am->m", step, step)) < tol**0.5
        if done.any():
            R[:, :, active[done]] = Ra[:, :, done]
            converged[active[done]] = True
            active, Ra, da = active[~done], Ra[:, :, ~done], da[:, ~done]
        if active.size == 0:
            break
    R[:, :, active] = Ra  # the last iterate of those that did not converge
    J, dist = _length_jacobian(R, home, A)
    N = gram3(J)
    if not all(np.isfinite(x).all() for x in N):
        # as numpy's eigvalsh did here: parameters (or readings) that describe no mechanism
        bad = int(np.count_nonzero(~np.isfinite(np.array(N)).all(axis=0)))
        raise np.linalg.LinAlgError(
            f"forward kinematics failed: the length Jacobian is not finite at {bad} of {m} "
            "poses (the parameters or readings describe no mechanism)"
        )
    sig = np.sqrt(np.maximum(eigmin_sym3(*N), 0.0))
    rms = np.sqrt(np.mean((dist - dc) ** 2, axis=0))
    return ForwardSolution(np.ascontiguousarray(np.moveaxis(R, -1, 0)), rms, sig, converged)


def _frame(b1: np.ndarray, b2: np.ndarray) -> np.ndarray:
    """Orthonormal frames (3, 3, m) of point pairs b1, b2 (3, m): ``F[i, c]`` the i-th
    component of column c; the columns lie along b1, in the b1-b2 plane, along b1 x b2."""
    e1 = b1 / np.sqrt(np.einsum("im,im->m", b1, b1))
    e3 = cross3(b1, b2)
    e3 /= np.sqrt(np.einsum("im,im->m", e3, e3))
    return np.stack([e1, cross3(e3, e1), e3], axis=1)


def leg_vectors(Rc: np.ndarray, home: np.ndarray, A: np.ndarray):
    """The legs of m poses, component-major (the pose index last).

    Parameters
    ----------
    Rc : ndarray, shape (3, 3, m)
        Rotations, ``Rc[i, j]`` the (m,) entries of row i, column j.
    home : ndarray, shape (2, 3)
        The plate points at home, mm (:func:`plate_home`).
    A : ndarray, shape (4, 3)
        The base points, mm (:func:`base_points`).

    Returns
    -------
    B : ndarray, shape (3, 4, m)
        The plate end of each leg, mm.
    u : ndarray, shape (3, 4, m)
        Unit vectors from A_i to it.
    dist : ndarray, shape (4, m)
        Leg lengths, mm.
    """
    Bp = [matvec3(Rc, h) for h in home]  # (3, m) each
    B = np.stack([Bp[b] for b in LEG_POINT], axis=1)
    diff = B - A.T[:, :, None]
    dist = np.sqrt(diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2])
    return B, diff / dist, dist


def _length_jacobian(Rc: np.ndarray, home: np.ndarray, A: np.ndarray):
    """d(length)/dw (3, 4, m) for left rotation increments w (rad), ``B x u``, and the
    lengths (4, m) in mm, at rotations Rc (3, 3, m)."""
    B, u, dist = leg_vectors(Rc, home, A)
    return cross3(B, u), dist


def in_stroke(lengths: np.ndarray, p: np.ndarray, stroke_mm: float = STROKE_MM) -> np.ndarray:
    """Whether each length is within ``d0_i +- stroke_mm``.

    Parameters
    ----------
    lengths : array_like, shape (m, 4)
        Actuator lengths, mm.
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), in the order of
        :data:`~loopcal.calibration.parameters.NAMES`. Only the offsets d0 are used.
    stroke_mm : float, default STROKE_MM
        Half the stroke, mm (37.5).

    Returns
    -------
    ndarray of bool, shape (m, 4)
    """
    return np.abs(np.asarray(lengths) - p[SL_OFFSET]) <= stroke_mm


#: the largest ``|value|`` a length parameter of this mechanism can plausibly have, mm: ten
#: times the reference design's size (its plate radius is 100 mm)
PLAUSIBLE_MM = 1000.0
#: the largest plausible gain, mm/V (the reference design's are 3.75 mm/V)
PLAUSIBLE_GAIN = 100.0


def check_geometry(p: np.ndarray) -> np.ndarray:
    """Validate a full parameter vector as a description of this mechanism.

    Beyond :func:`loopcal.calibration.parameters.check_vector` (shape, finite, positive plate
    sizes and gains, a plate triangle): every length within +-:data:`PLAUSIBLE_MM` mm, every
    gain at most :data:`PLAUSIBLE_GAIN` mm/V, and at the home pose (identity rotation) every
    actuator's length inside its sensor's range ``d0 +- 10 V * S``. A vector that fails
    would make forward kinematics meaningless (or fail outright).

    Parameters
    ----------
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V), in the order of
        :data:`~loopcal.calibration.parameters.NAMES`.

    Returns
    -------
    ndarray, shape (20,)
        The vector as a float array.

    Raises
    ------
    ParameterError
        If any check fails; the message names the parameters to look at.
    """
    p = check_vector(p)
    for name, value in zip(NAMES, p, strict=True):
        limit = PLAUSIBLE_GAIN if UNITS[name] == "mm/V" else PLAUSIBLE_MM
        if abs(value) > limit:
            raise ParameterError(
                f"{name} = {value:g} {UNITS[name]} is outside the plausible range "
                f"-{limit:g}..{limit:g} {UNITS[name]} for this mechanism"
            )
    home = inverse_kinematics(np.eye(3), p)[0]
    volts = lengths_to_volts(home, p)
    for i in np.flatnonzero(np.abs(volts) > STROKE_VOLTS):
        n = i + 1
        point = "B1" if LEG_POINT[i] == 0 else "B2"
        raise ParameterError(
            f"actuator {n} would be {home[i]:.1f} mm long at the home pose (A{n} to {point}), "
            f"outside its sensor's range d0{n} +- 10 V * S{n} = "
            f"{p[SL_OFFSET][i] - STROKE_VOLTS * p[SL_GAIN][i]:.1f}.."
            f"{p[SL_OFFSET][i] + STROKE_VOLTS * p[SL_GAIN][i]:.1f} mm: check the A{n} "
            f"coordinates, k1..k3, d0{n} and S{n}"
        )
    return p
