"""Closed-form 3x3 (and 4x3) linear algebra for many poses at once, component-major.

Every function takes and returns arrays whose LAST axis runs over the m poses: a vector is
``(3, m)``, a matrix ``(3, 3, m)`` (``M[i, j]`` the (m,) entries of row i, column j) and a
symmetric 3x3 matrix is passed as its six distinct entries ``(a00, a11, a22, a01, a02,
a12)``, each (m,) (or anything broadcasting against (m,)). Each operation is then a few
dozen elementwise operations over contiguous pose arrays, where the batched routines of
``numpy.linalg`` (``inv``, ``solve``, ``svd``, ``eigvalsh`` on (m, 3, 3)) and
``scipy.spatial.transform.Rotation`` pay a call per pose. The results agree with those
routines to rounding (tests/calibration/test_smallmat.py).

Nothing here raises on a singular or indefinite matrix: the affected poses get NaN or inf,
and callers test ``np.isfinite``.
"""

from __future__ import annotations

import numpy as np

#: below this rotation angle (rad), Rodrigues' coefficients come from their Taylor series
#: (the truncation errors, below theta^6 / 5040, are under 1e-21 there)
_SMALL_ANGLE = 1e-3


def rotvec_to_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrices ``exp([w]x)`` of rotation vectors (Rodrigues' formula).

    Parameters
    ----------
    w : array_like, shape (3, m)
        Rotation vectors, rad.

    Returns
    -------
    ndarray, shape (3, 3, m)
        ``cos(t) I + sin(t)/t [w]x + (1 - cos(t))/t^2 w w^T`` with ``t = |w|``: the same as
        ``Rotation.from_rotvec(w.T).as_matrix()`` moved to component-major. Below 1e-3 rad
        the coefficients come from their Taylor series.
    """
    w = np.asarray(w, dtype=float)
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    # the Taylor series everywhere (a solver's late steps are all small), the trigonometric
    # functions where the angle is not
    c = 1.0 - t2 / 2.0 * (1.0 - t2 / 12.0 * (1.0 - t2 / 30.0))
    a = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0)
    b = 0.5 - t2 / 24.0 * (1.0 - t2 / 30.0)
    large = t2 >= _SMALL_ANGLE**2
    if large.any():
        t = np.sqrt(t2[large])
        cos_t = np.cos(t)
        c[large] = cos_t
        a[large] = np.sin(t) / t
        b[large] = (1.0 - cos_t) / (t * t)
    bx, by, bz = b * w[0], b * w[1], b * w[2]
    ax, ay, az = a * w[0], a * w[1], a * w[2]
    bxy, bxz, byz = bx * w[1], bx * w[2], by * w[2]
    E = np.empty((3, 3) + t2.shape)
    E[0, 0], E[0, 1], E[0, 2] = c + bx * w[0], bxy - az, bxz + ay
    E[1, 0], E[1, 1], E[1, 2] = bxy + az, c + by * w[1], byz - ax
    E[2, 0], E[2, 1], E[2, 2] = bxz - ay, byz + ax, c + bz * w[2]
    return E


def matmul3(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Products ``A_k B_k`` of 3x3 matrices.

    Parameters
    ----------
    A, B : ndarray, shape (3, 3, m) or (3, 3, 1)
        Matrices, component-major.

    Returns
    -------
    ndarray, shape (3, 3, m)
    """
    out = np.empty(np.broadcast_shapes(A.shape, B.shape))
    for i in range(3):
        np.multiply(A[i, 0], B[0], out=out[i])
        out[i] += A[i, 1] * B[1]
        out[i] += A[i, 2] * B[2]
    return out


def matvec3(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Products ``A_k x_k`` of 3x3 matrices and vectors.

    Parameters
    ----------
    A : ndarray, shape (3, 3, m) or (3, 3, 1)
        Matrices, component-major.
    x : ndarray, shape (3, m), (3, 1) or (3,)
        Vectors; (3,) is one vector for every k.

    Returns
    -------
    ndarray, shape (3, m)
    """
    return A[:, 0] * x[0] + A[:, 1] * x[1] + A[:, 2] * x[2]


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross products over the first axis.

    Parameters
    ----------
    a, b : ndarray, shape (3, ...)
        Vectors, broadcasting against each other after the first axis.

    Returns
    -------
    ndarray, shape (3, ...)
        ``a x b``.
    """
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Dot products over the first axis.

    Parameters
    ----------
    a, b : ndarray, shape (3, ...)
        Vectors, as in :func:`cross3`.

    Returns
    -------
    ndarray, shape (...)
        ``a[0] b[0] + a[1] b[1] + a[2] b[2]``.
    """
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def gram3(J: np.ndarray):
    """The six distinct entries of ``J^T J`` for matrices J with three columns.

    Parameters
    ----------
    J : ndarray, shape (3, r, m)
        Matrices of r rows, component-major, column first: ``J[a, i]`` the (m,) entries of
        row i, column a.

    Returns
    -------
    tuple of ndarray
        ``(n00, n11, n22, n01, n02, n12)``, each (m,).
    """
    pairs = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
    return tuple(np.einsum("im,im->m", J[a], J[b]) for a, b in pairs)


def cholesky3(a00, a11, a22, a01, a02, a12):
    """Cholesky factor of symmetric positive definite 3x3 matrices, ``A = L L^T``.

    Parameters
    ----------
    a00, a11, a22, a01, a02, a12 : ndarray, shape (m,)
        The six distinct entries of A.

    Returns
    -------
    tuple of ndarray
        ``(l00, l10, l11, l20, l21, l22)``, the lower triangle of L, each (m,). NaN where A
        is not positive definite.
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        l00 = np.sqrt(a00)
        l10 = a01 / l00
        l20 = a02 / l00
        l11 = np.sqrt(a11 - l10 * l10)
        l21 = (a12 - l20 * l10) / l11
        l22 = np.sqrt(a22 - l20 * l20 - l21 * l21)
    return l00, l10, l11, l20, l21, l22


def solve_sym3(a00, a11, a22, a01, a02, a12, b: np.ndarray) -> np.ndarray:
    """Solutions of ``A x = b`` for symmetric 3x3 A, by the adjugate (Cramer's rule).

    Parameters
    ----------
    a00, a11, a22, a01, a02, a12 : ndarray, shape (m,)
        The six distinct entries of A.
    b : ndarray, shape (3, m)
        Right-hand sides.

    Returns
    -------
    ndarray, shape (3, m)
        x: the same as ``np.linalg.solve`` on (m, 3, 3) to rounding while A is well
        conditioned; inf or NaN where A is exactly singular (where ``np.linalg.solve``
        raises).
    """
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    with np.errstate(invalid="ignore", divide="ignore"):
        inv_det = 1.0 / det
        return np.array(
            [
                (c00 * b[0] + c01 * b[1] + c02 * b[2]) * inv_det,
                (c01 * b[0] + c11 * b[1] + c12 * b[2]) * inv_det,
                (c02 * b[0] + c12 * b[1] + c22 * b[2]) * inv_det,
            ]
        )


def eigmin_sym3(a00, a11, a22, a01, a02, a12) -> np.ndarray:
    """The smallest eigenvalue of symmetric 3x3 matrices.

    Parameters
    ----------
    a00, a11, a22, a01, a02, a12 : ndarray, shape (m,)
        As for :func:`cholesky3`.

    Returns
    -------
    ndarray, shape (m,)

    Notes
    -----
    The trigonometric solution of the characteristic cubic (Smith, 1961), polished by one
    Newton step on ``det(A - lambda I)``, which restores the digits the trigonometric form
    loses when the two largest eigenvalues (nearly) coincide. Agrees with
    ``np.linalg.eigvalsh(A)[:, 0]`` to about 1e-13 of the largest eigenvalue, except where
    the smallest eigenvalue is (nearly) double: a double root of the cubic is known only to
    about 1e-8 relative (forward kinematics compares it with a threshold; the mechanism's
    length Jacobian has a double smallest singular value only by coincidence).
    """
    q = (a00 + a11 + a22) / 3.0
    off = a01 * a01 + a02 * a02 + a12 * a12
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    pp = np.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * off) / 6.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        det_b = (
            b00 * (b11 * b22 - a12 * a12)
            - a01 * (a01 * b22 - a12 * a02)
            + a02 * (a01 * a12 - b11 * a02)
        )
        r = np.clip(0.5 * det_b / (pp * pp * pp), -1.0, 1.0)
        phi = np.arccos(r) / 3.0
        flat = ~(pp > 0)  # a multiple of the identity
        lam = np.where(flat, q, q + 2.0 * pp * np.cos(phi + 2.0 * np.pi / 3.0))
        gap = np.where(flat, 0.0, q + 2.0 * pp * np.cos(phi - 2.0 * np.pi / 3.0) - lam)
        # one Newton step on f(l) = det(A - l I), f'(l) = -(sum of the principal 2x2
        # minors), where the root is simple: well inside the gap to the middle eigenvalue
        d0, d1, d2 = a00 - lam, a11 - lam, a22 - lam
        m00, m11, m22 = d1 * d2 - a12 * a12, d0 * d2 - a02 * a02, d0 * d1 - a01 * a01
        f = d0 * m00 - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02)
        step = f / -(m00 + m11 + m22)
    polish = np.isfinite(step) & (np.abs(step) <= 0.25 * gap)
    return np.where(polish, lam - step, lam)


def null_vector_4x3(J: np.ndarray) -> np.ndarray:
    """Unit vectors orthogonal to the three columns of 4x3 matrices.

    Parameters
    ----------
    J : ndarray, shape (3, 4, m)
        ``J[a, i]`` the (m,) entries of row i, column a (component-major: column first).

    Returns
    -------
    ndarray, shape (4, m)
        q, the generalised cross product of the columns, ``q_i = (-1)^i det(J without row
        i)``, normalised: the left singular vector of J for its zero singular value, as
        ``np.linalg.svd`` gives it, up to sign. NaN where the columns are linearly dependent
        (no unique direction).
    """
    c0, c1, c2 = J[0], J[1], J[2]  # (4, m) each: the columns
    # the 2x2 minors of the last two columns, rows (j, k); each 3x3 minor expands along c0
    d = {(j, k): c1[j] * c2[k] - c1[k] * c2[j] for j in range(4) for k in range(j + 1, 4)}
    q = np.array(
        [
            c0[1] * d[2, 3] - c0[2] * d[1, 3] + c0[3] * d[1, 2],
            -(c0[0] * d[2, 3] - c0[2] * d[0, 3] + c0[3] * d[0, 2]),
            c0[0] * d[1, 3] - c0[1] * d[0, 3] + c0[3] * d[0, 1],
            -(c0[0] * d[1, 2] - c0[1] * d[0, 2] + c0[2] * d[0, 1]),
        ]
    )
    norm = np.sqrt(np.einsum("im,im->m", q, q))
    with np.errstate(invalid="ignore", divide="ignore"):
        return q / np.where(norm > 0, norm, np.nan)
