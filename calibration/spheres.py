"""Intersection of three spheres, one centred at the origin, with forward-mode derivatives.

Used by the closed-loop residuals (MODEL.md section 5) and by forward kinematics. The point x
solves ``|x| = r0``, ``|x - P1| = r1``, ``|x - P2| = r2``. Writing
``x = a P1 + b P2 + g n`` with ``n = P1 x P2``, the two plane equations fix a and b, and the
first sphere fixes ``g = +-h / |n|`` with ``h^2 = r0^2 - |a P1 + b P2|^2``. The two mirror
solutions lie ``2 h`` apart; as h goes to zero they merge (a singular configuration) and the
derivatives grow like ``1 / h``.

Derivatives come from implicit differentiation of the sphere equations:
``[x; x - P1; x - P2] dx = [r0 dr0; (x - P1).dP1 + r1 dr1; (x - P2).dP2 + r2 dr2]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SphereIntersection:
    """point: (m, 3); jacobian: (m, 3, q) derivative of the point, or None if not asked for;
    separation: (m,) distance between the two mirror solutions (0 where none exists), mm;
    feasible: (m,) False where the spheres do not meet: the point is then the closest
    approach in the plane (O, P1, P2), which keeps the residuals continuous, and its
    derivative is that of the closest approach."""

    point: np.ndarray
    jacobian: np.ndarray | None
    separation: np.ndarray
    feasible: np.ndarray


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def _vecmat(v: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Row vectors v (m, 3) times matrices M (3, q) or (m, 3, q): (m, q)."""
    return (v[:, None, :] @ M)[:, 0]


def _solve3(M: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve M (m, 3, 3) X = rhs (m, 3, q) by the adjugate; singular rows give NaN.

    Much faster than a batched LAPACK solve for many tiny systems."""
    r0, r1, r2 = M[:, 0], M[:, 1], M[:, 2]
    adj = np.stack([np.cross(r1, r2), np.cross(r2, r0), np.cross(r0, r1)], axis=2)
    det = _dot(r0, adj[:, :, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = adj / np.where(det != 0, det, np.nan)[:, None, None]
    return inv @ rhs


def intersect_three_spheres(
    r0: np.ndarray | float,
    P1: np.ndarray,
    r1: np.ndarray | float,
    P2: np.ndarray,
    r2: np.ndarray | float,
    ref: np.ndarray,
    *,
    d_r0: np.ndarray | None = None,
    d_P1: np.ndarray | None = None,
    d_r1: np.ndarray | None = None,
    d_P2: np.ndarray | None = None,
    d_r2: np.ndarray | None = None,
) -> SphereIntersection:
    """Intersect sphere(O, r0), sphere(P1, r1), sphere(P2, r2), vectorised over m problems.

    Radii are scalars or (m,), centres (3,) or (m, 3), all in mm. ``ref`` (m, 3) selects the
    branch: the solution on the same side of the plane (O, P1, P2) as ``ref``, which is the one
    nearer to ``ref``. The ``d_*`` arguments, if any is given, are derivatives with respect to
    q parameters: radii (q,) or (m, q), centres (3, q) or (m, 3, q); missing ones are zero.
    """
    P1 = np.asarray(P1, dtype=float)
    P2 = np.asarray(P2, dtype=float)
    ref = np.asarray(ref, dtype=float)
    m = ref.shape[0]
    P1 = np.broadcast_to(P1, (m, 3))
    P2 = np.broadcast_to(P2, (m, 3))
    r0 = np.broadcast_to(np.asarray(r0, dtype=float), (m,))
    r1 = np.broadcast_to(np.asarray(r1, dtype=float), (m,))
    r2 = np.broadcast_to(np.asarray(r2, dtype=float), (m,))

    n = np.cross(P1, P2)
    nn = _dot(n, n)
    g11, g12, g22 = _dot(P1, P1), _dot(P1, P2), _dot(P2, P2)
    c1 = 0.5 * (r0 * r0 - r1 * r1 + g11)
    c2 = 0.5 * (r0 * r0 - r2 * r2 + g22)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (c1 * g22 - c2 * g12) / nn
        b = (c2 * g11 - c1 * g12) / nn
    q = a[:, None] * P1 + b[:, None] * P2
    h2 = r0 * r0 - _dot(q, q)
    feasible = (h2 >= 0) & (nn > 0)
    h = np.sqrt(np.where(feasible, h2, 0.0))
    side = np.where(_dot(n, ref - q) >= 0, 1.0, -1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = q + (side * h / np.sqrt(nn))[:, None] * n
    separation = 2.0 * h

    jac = None
    if any(v is not None for v in (d_r0, d_P1, d_r1, d_P2, d_r2)):
        q_dim = next(np.shape(v)[-1] for v in (d_r0, d_P1, d_r1, d_P2, d_r2) if v is not None)
        rhs = np.zeros((m, 3, q_dim))
        e1, e2 = x - P1, x - P2
        if d_r0 is not None:
            rhs[:, 0] += r0[:, None] * d_r0
        if d_r1 is not None:
            rhs[:, 1] += r1[:, None] * d_r1
        if d_r2 is not None:
            rhs[:, 2] += r2[:, None] * d_r2
        if d_P1 is not None:
            rhs[:, 1] += _vecmat(e1, d_P1)
        if d_P2 is not None:
            rhs[:, 2] += _vecmat(e2, d_P2)
        M = np.stack([x, e1, e2], axis=1)
        # Where the spheres miss each other, x is the closest approach in the plane
        # (O, P1, P2): differentiate the two plane equations and n . x = 0 instead.
        miss = ~(h > 0)
        if miss.any():
            M[miss, 0] = n[miss]
            M[miss, 1] = P1[miss]
            M[miss, 2] = P2[miss]
            dn = np.zeros((m, 3, q_dim))
            if d_P1 is not None:
                dn += np.cross(np.broadcast_to(d_P1, (m, 3, q_dim)), P2[:, :, None], axis=1)
            if d_P2 is not None:
                dn += np.cross(P1[:, :, None], np.broadcast_to(d_P2, (m, 3, q_dim)), axis=1)
            plane = rhs[:, 1:] - rhs[:, :1]  # P_i . dx = r0 dr0 - r_i dr_i - (x - P_i) . dP_i
            rhs[miss, 0] = -_vecmat(x[miss], dn[miss])
            rhs[miss, 1:] = -plane[miss]
        jac = _solve3(M, rhs)
    return SphereIntersection(x, jac, separation, feasible)
