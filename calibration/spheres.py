"""Intersection of three spheres, one centred at the origin, and its adjoint derivative.

Used by the closed-loop residuals (docs/model.md section 5) and by forward kinematics. The point x
solves ``|x| = r0``, ``|x - P1| = r1``, ``|x - P2| = r2``. Writing
``x = a P1 + b P2 + g n`` with ``n = P1 x P2``, the two plane equations fix a and b, and the
first sphere fixes ``g = +-h / |n|`` with ``h^2 = r0^2 - |a P1 + b P2|^2``. The two mirror
solutions lie ``2 h`` apart; as h goes to zero they merge (a singular configuration) and the
derivatives grow like ``1 / h``.

Derivatives come from implicit differentiation of the sphere equations::

    M dx = rhs,  M = [x; x - P1; x - P2],
    rhs = [r0 dr0; (x - P1).dP1 + r1 dr1; (x - P2).dP2 + r2 dr2].

Where the spheres miss each other (inconsistent readings, or parameters far off), x is taken
as the closest approach in the plane (O, P1, P2), which keeps residuals continuous; its
derivative follows from the two plane equations and ``n . x = 0``:
``M = [n; P1; P2]``, ``rhs = [-x.dn; rhs_0 - rhs_1; rhs_0 - rhs_2]``.

The residuals need ``g . dx`` for one row vector g per pose (the adjoint, or reverse mode):
``g . dx = lam . rhs`` with ``lam = M^-T g``, which :func:`adjoint` returns as coefficients of
dr0, dr1, dr2, dP1 and dP2. Arrays here are component-major (points ``(3, m)``) so every
operation runs over contiguous pose arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .smallmat import cross3, dot3


@dataclass(frozen=True)
class Solved:
    """One batch of intersections, component-major (the pose index last), with what
    :func:`adjoint` needs to differentiate them.

    Attributes
    ----------
    x : ndarray, shape (3, m)
        The chosen solution, mm (where the spheres miss, the closest approach in the plane
        of the three centres).
    separation : ndarray, shape (m,)
        Distance between the two mirror solutions, mm (0 where there is none).
    feasible : ndarray of bool, shape (m,)
        The spheres meet (and the centres are not collinear with the origin).
    r0, r1, r2 : float or ndarray, shape (m,)
        The radii solved for, as given, mm.
    P1, P2 : ndarray, shape (3, m) or (3, 1)
        The centres solved for, as given, mm.
    miss : ndarray of bool, shape (m,)
        No separation between the branches (``h`` is zero: the spheres miss or touch).
    n : ndarray, shape (3, m)
        ``P1 x P2``, the normal of the plane (O, P1, P2).
    """

    x: np.ndarray
    separation: np.ndarray
    feasible: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    r2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    miss: np.ndarray
    n: np.ndarray


def solve(r0, P1, r1, P2, r2, ref: np.ndarray) -> Solved:
    """Intersect sphere(O, r0), sphere(P1, r1), sphere(P2, r2) for m poses at once.

    Parameters
    ----------
    r0 : float or ndarray, shape (m,)
        Radius of the sphere about the origin, mm.
    P1 : ndarray, shape (3, m) or (3, 1)
        Centre of the second sphere, mm.
    r1 : float or ndarray, shape (m,)
        Its radius, mm.
    P2 : ndarray, shape (3, m) or (3, 1)
        Centre of the third sphere, mm.
    r2 : float or ndarray, shape (m,)
        Its radius, mm.
    ref : ndarray, shape (3, m) or (3, 1)
        Picks the branch: the solution on the same side of the plane (O, P1, P2) as
        ``ref``, which is the one nearer to it.

    Returns
    -------
    Solved
        The solutions, with what :func:`adjoint` needs. Nothing raises: where the spheres
        miss, the point is the closest approach in the plane (``feasible`` False).
    """
    n = cross3(P1, P2)
    nn = dot3(n, n)
    g11, g12, g22 = dot3(P1, P1), dot3(P1, P2), dot3(P2, P2)
    r00 = r0 * r0
    c1 = 0.5 * (r00 - r1 * r1 + g11)
    c2 = 0.5 * (r00 - r2 * r2 + g22)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (c1 * g22 - c2 * g12) / nn
        b = (c2 * g11 - c1 * g12) / nn
    q = a * P1 + b * P2
    h2 = r00 - dot3(q, q)
    feasible = (h2 >= 0) & (nn > 0)
    h = np.sqrt(np.where(feasible, h2, 0.0))
    side = np.where(dot3(n, ref - q) >= 0, 1.0, -1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        x = q + (side * h / np.sqrt(nn)) * n
    return Solved(x, 2.0 * h, feasible, r0, r1, r2, P1, P2, ~(h > 0), n)


def adjoint(s: Solved, g: np.ndarray):
    """Coefficients of ``g . dx`` for row vectors g: the reverse-mode derivative.

    Parameters
    ----------
    s : Solved
        Intersections from :func:`solve`.
    g : ndarray, shape (3, m)
        One row vector per pose (for the residuals, the gradient of a residual with
        respect to the solution x).

    Returns
    -------
    a0, a1, a2 : ndarray, shape (m,)
        Coefficients of dr0, dr1, dr2.
    b1, b2 : ndarray, shape (3, m)
        Coefficients of dP1, dP2.

    Notes
    -----
    Per pose, ``g . dx = a0 dr0 + a1 dr1 + a2 dr2 + b1 . dP1 + b2 . dP2``, from
    ``lam = M^-T g`` (module docstring). NaN where the configuration is degenerate.
    """
    e1, e2 = s.x - s.P1, s.x - s.P2
    rows = (s.x, e1, e2)
    if s.miss.any():
        rows = tuple(
            np.where(s.miss, alt, row) for alt, row in zip((s.n, s.P1, s.P2), rows, strict=True)
        )
    # M^-1 by the adjugate: columns r1 x r2, r2 x r0, r0 x r1 over det(M); lam = M^-T g.
    adj = (cross3(rows[1], rows[2]), cross3(rows[2], rows[0]), cross3(rows[0], rows[1]))
    det = dot3(rows[0], adj[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / np.where(det != 0, det, np.nan)
    lam = [dot3(c, g) * inv_det for c in adj]
    a0, a1, a2 = lam[0] * s.r0, lam[1] * s.r1, lam[2] * s.r2
    b1, b2 = lam[1] * e1, lam[2] * e2
    if s.miss.any():
        w = s.miss
        a0 = np.where(w, (lam[1] + lam[2]) * s.r0, a0)
        a1 = np.where(w, -a1, a1)
        a2 = np.where(w, -a2, a2)
        b1 = np.where(w, -lam[0] * cross3(s.P2, s.x) - b1, b1)
        b2 = np.where(w, -lam[0] * cross3(s.x, s.P1) - b2, b2)
    return a0, a1, a2, b1, b2
