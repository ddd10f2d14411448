"""The closed-form small-matrix helpers (calibration/smallmat.py) against the batched numpy
and scipy routines they replace in the hot paths."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from loopcal.calibration import implicit, smallmat
from loopcal.calibration.kinematics import forward_kinematics, inverse_kinematics
from loopcal.calibration.parameters import NOMINAL
from loopcal.calibration.simulate import sample_workspace


def sym_entries(A: np.ndarray):
    """(a00, a11, a22, a01, a02, a12) of (m, 3, 3) symmetric matrices."""
    return A[:, 0, 0], A[:, 1, 1], A[:, 2, 2], A[:, 0, 1], A[:, 0, 2], A[:, 1, 2]


def spd(rng: np.random.Generator, m: int, scale: float = 1.0) -> np.ndarray:
    """m random symmetric positive definite 3x3 matrices of spread conditioning."""
    X = rng.standard_normal((m, 4, 3)) * rng.uniform(0.01, 10.0, (m, 1, 3))
    return scale * np.swapaxes(X, 1, 2) @ X


def test_rodrigues_matches_scipy_rotation_for_large_small_and_zero_angles():
    rng = np.random.default_rng(1)
    axes = rng.standard_normal((400, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [rng.uniform(0, np.pi, 100), 10.0 ** rng.uniform(-12, -2, 290), [1e-3] * 5, [0.0] * 5]
    )
    w = axes * angles[:, None]
    E = smallmat.rotvec_to_matrix(w.T)
    ref = Rotation.from_rotvec(w).as_matrix()
    assert np.abs(np.moveaxis(E, -1, 0) - ref).max() < 1e-15 * 4


def test_matmul_matvec_cross_match_numpy():
    rng = np.random.default_rng(2)
    A, B = rng.standard_normal((2, 50, 3, 3))
    x, y = rng.standard_normal((2, 50, 3))
    AB = smallmat.matmul3(np.moveaxis(A, 0, -1), np.moveaxis(B, 0, -1))
    assert np.allclose(np.moveaxis(AB, -1, 0), A @ B, rtol=0, atol=1e-14)
    Ax = smallmat.matvec3(np.moveaxis(A, 0, -1), x.T)
    assert np.allclose(Ax.T, (A @ x[..., None])[..., 0], rtol=0, atol=1e-14)
    assert np.allclose(smallmat.cross3(x.T, y.T).T, np.cross(x, y), rtol=0, atol=1e-14)


def test_cholesky_matches_numpy_and_flags_indefinite_matrices():
    rng = np.random.default_rng(3)
    A = spd(rng, 200, 1e3)
    l00, l10, l11, l20, l21, l22 = smallmat.cholesky3(*sym_entries(A))
    L = np.zeros_like(A)
    L[:, 0, 0], L[:, 1, 0], L[:, 1, 1], L[:, 2, 0], L[:, 2, 1], L[:, 2, 2] = (
        l00, l10, l11, l20, l21, l22,
    )  # fmt: skip
    ref = np.linalg.cholesky(A)
    assert np.allclose(L, ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
    bad = A.copy()
    bad[:5] = -bad[:5]  # negative definite
    out = smallmat.cholesky3(*sym_entries(bad))
    assert not np.isfinite(out[0][:5]).any() and np.isfinite(np.array(out)[:, 5:]).all()


def test_symmetric_solve_matches_numpy_solve_and_inverse():
    rng = np.random.default_rng(4)
    A = spd(rng, 300)
    b = rng.standard_normal((300, 3))
    x = smallmat.solve_sym3(*sym_entries(A), b.T).T
    ref = np.linalg.solve(A, b[..., None])[..., 0]
    cond = np.linalg.cond(A)
    err = np.linalg.norm(x - ref, axis=1) / np.linalg.norm(ref, axis=1)
    assert np.all(err <= 1e-15 * cond * 50), (err / cond).max()
    # the identity's columns: the inverse
    inv = np.stack([smallmat.solve_sym3(*sym_entries(A), np.eye(3)[:, [j]]) for j in range(3)])
    inv = np.moveaxis(inv, -1, 0).transpose(0, 2, 1)
    ref_inv = np.linalg.inv(A)
    rel = np.abs(inv - ref_inv).max(axis=(1, 2)) / np.abs(ref_inv).max(axis=(1, 2))
    assert np.all(rel <= 1e-15 * cond * 50)
    # exactly singular: not finite (numpy raises)
    S = np.ones((1, 3, 3))
    assert not np.isfinite(smallmat.solve_sym3(*sym_entries(S), np.ones((3, 1)))).all()


def test_smallest_eigenvalue_matches_eigvalsh():
    rng = np.random.default_rng(5)
    A = spd(rng, 500, 1e4)
    # hard cases: multiple eigenvalues, diagonal matrices, a zero matrix
    Q = Rotation.random(5, random_state=6).as_matrix()
    special = np.stack(
        [
            Q[0] @ np.diag([5.0, 5.0, 1.0]) @ Q[0].T,
            Q[1] @ np.diag([3.0, 3.0, 3.0]) @ Q[1].T,
            Q[2] @ np.diag([1e4, 1e4, 4.0]) @ Q[2].T,
            np.diag([4.0, 1.0, 9.0]),
            np.zeros((3, 3)),
        ]
    )
    A = np.concatenate([A, special])
    A = 0.5 * (A + np.swapaxes(A, 1, 2))
    lam = smallmat.eigmin_sym3(*sym_entries(A))
    ref = np.linalg.eigvalsh(A)
    scale = np.maximum(np.abs(ref).max(axis=1), 1e-300)
    assert np.all(np.abs(lam - ref[:, 0]) <= 1e-13 * scale)
    # a double smallest eigenvalue: a double root of the cubic, known to ~1e-8 relative
    double = np.stack(
        [Q[3] @ np.diag([7.0, 2.0, 2.0]) @ Q[3].T, Q[4] @ np.diag([1e4, 4, 4]) @ Q[4].T]
    )
    double = 0.5 * (double + np.swapaxes(double, 1, 2))
    assert np.allclose(smallmat.eigmin_sym3(*sym_entries(double)), [2.0, 4.0], rtol=1e-7, atol=0)


@pytest.mark.parametrize("m", [1, 64])
def test_loop_direction_matches_the_singular_vector(m):
    rng = np.random.default_rng(7)
    J = rng.standard_normal((m, 4, 3)) * rng.uniform(0.1, 30.0, (m, 4, 1))
    q = smallmat.null_vector_4x3(np.moveaxis(J, 0, -1).transpose(1, 0, 2)).T  # (m, 4)
    U = np.linalg.svd(J, full_matrices=True)[0][:, :, 3]
    sign = np.sign(np.einsum("mi,mi->m", q, U))
    assert np.allclose(q, U * sign[:, None], rtol=0, atol=1e-13)
    assert np.abs(np.einsum("mi,mia->ma", q, J)).max() < 1e-12 * np.abs(J).max()
    # the public function (pose-major) too, with the SVD's answer where columns are dependent
    J2 = J.copy()
    J2[0, :, 2] = 2 * J2[0, :, 1]
    q2 = implicit.loop_direction(J2)
    assert np.isfinite(q2).all() and np.allclose(np.linalg.norm(q2, axis=1), 1.0)
    assert np.abs(np.einsum("mi,mia->ma", q2, J2)).max() < 1e-12 * np.abs(J2).max()


def test_warm_started_forward_kinematics_finds_the_cold_solution():
    rng = np.random.default_rng(8)
    R = sample_workspace(200, rng, NOMINAL)
    d = inverse_kinematics(R, NOMINAL) + rng.normal(0.0, 0.15, (200, 4))
    cold = forward_kinematics(d, NOMINAL)
    exact = forward_kinematics(d, NOMINAL, tol=1e-26)  # steps down to 1e-13 rad
    nudge = Rotation.from_rotvec(rng.normal(0.0, 2e-3, (200, 3))).as_matrix()
    start = nudge @ cold.rotations
    warm = forward_kinematics(d, NOMINAL, start=start)
    assert np.array_equal(start, nudge @ cold.rotations)  # the caller's start is left alone
    one = forward_kinematics(d[:1], NOMINAL, start=start[:1])
    assert np.array_equal(start[:1], (nudge @ cold.rotations)[:1]) and one.converged.all()
    assert cold.converged.all() and warm.converged.all()
    # both stop once a step is below 1e-6 rad: within 1e-8 of the solution
    for fk in (cold, warm):
        assert np.abs(fk.rotations - exact.rotations).max() < 1e-8
        assert np.allclose(fk.sigma_min, exact.sigma_min, rtol=1e-8, atol=0)
        assert np.allclose(fk.rms_mm, exact.rms_mm, rtol=1e-6, atol=1e-12)


def test_forward_kinematics_of_no_mechanism_raises_as_before():
    """A1x = 1e300 passes the vector check but leaves nothing finite: LinAlgError, as numpy's
    eigvalsh raised there (the recorder reports it and keeps writing raw scans)."""
    p = NOMINAL.copy()
    p[0] = 1e300
    with np.errstate(all="ignore"), pytest.raises(np.linalg.LinAlgError, match="not finite"):
        forward_kinematics(np.full((5, 4), 97.4), p)
