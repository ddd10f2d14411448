"""Pose selection: choose K of N candidate poses that best identify the free parameters
(docs/model.md section 8).

Every pose k contributes ``A_k = G_k^T G_k`` to the information matrix ``M(S) = sum_{k in S} A_k``
of a set S, where ``G_k`` (4, n) is the pose's block of the scaled Jacobian. One fixed column
scaling ``H`` (that of the whole candidate pool, see :mod:`loopcal.calibration.observability`) is
used for every subset, so that subsets are compared on one scale. The singular values of a subset's
scaled Jacobian are the square roots of the eigenvalues of ``M(S)``.

Algorithm:

1. Convex relaxation: maximise ``lambda_min(sum_k w_k A_k)`` over ``0 <= w_k <= 1``,
   ``sum w = K``, by Frank-Wolfe on a soft-min smoothing of lambda_min.
2. The K largest relaxed weights start a Fedorov exchange: repeatedly remove one chosen pose
   and add the candidate that most improves the criterion, evaluated exactly on a shortlist
   ranked by the first-order gain, until no swap improves it. Swaps that would break the
   condition-number bound are refused (or, while it is broken, only swaps that lower it are
   taken).

Certified bound (criterion ``min_singular``). For any symmetric ``Z >= 0`` with trace one,
``lambda_min(M) <= <Z, M>``, hence for every K-subset
``lambda_min(M(S)) <= sum_{k in S} <Z, A_k> <= (sum of the K largest <Z, A_k>)``.
Every Z the relaxation produces gives such a bound; the smallest one is reported, as a bound
on the minimum singular value ``sqrt(.)``. Its minimum over Z equals the optimum of the
relaxation (minimax duality), so ``value / bound`` measures both the integrality gap and how
far the relaxation was solved; a ratio of 1 proves the chosen set optimal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import implicit
from .errors import InputError
from .observability import CONDITION_OK, ObservabilityIndices, as_rows, column_scales
from .parameters import ParameterModel
from .residuals import check_volts, loop_residuals, noise_directions, reference_points
from .simulate import NEAR_SINGULAR_MM

#: the criteria :func:`select_poses` can maximise (the indices of
#: :class:`~loopcal.calibration.observability.ObservabilityIndices`)
CRITERIA = ("min_singular", "condition", "volume", "noise_amplification", "a_optimality")


def _criterion_value(lam: np.ndarray, criterion: str, k: int) -> np.ndarray:
    """Criterion (larger is better) from ascending eigenvalues lam (..., n) of M."""
    lam = np.maximum(lam, 0.0)
    lo, hi = lam[..., 0], lam[..., -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        if criterion == "min_singular":
            return np.sqrt(lo)
        if criterion == "condition":
            return -np.sqrt(hi / lo)
        if criterion == "volume":
            return np.exp(0.5 * np.mean(np.log(lam), axis=-1)) / np.sqrt(k)
        if criterion == "noise_amplification":
            return lo / np.sqrt(hi)
        if criterion == "a_optimality":
            return -np.sum(1.0 / lam, axis=-1)
    raise InputError(f"unknown criterion {criterion!r}; choose one of {', '.join(CRITERIA)}")


def _condition(lam: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.maximum(lam[..., -1], 0) / np.maximum(lam[..., 0], 0))


@dataclass(frozen=True)
class Selection:
    """Result of :func:`select_poses`.

    Attributes
    ----------
    indices : ndarray of int, shape (K,)
        Chosen candidate indices, ascending.
    criterion : str
        The criterion maximised, one of :data:`CRITERIA`.
    value : float
        Its value for the chosen set on the pool's scale (``condition`` and
        ``a_optimality`` are reported as positive numbers, smaller better).
    min_singular : float
        Smallest singular value of the chosen set (pool scale).
    condition : float
        Condition number of the chosen set (pool scale).
    upper_bound : float or None
        Certified upper bound on the minimum singular value of any K-subset (pool scale);
        None without ``certify``.
    meets_condition : bool
        Whether ``condition`` is within the requested bound (the exchange first lowers the
        condition until it is, and reports honestly if it cannot).
    indices_own : ObservabilityIndices
        Observability indices of the chosen set with its own scaling, as the paper reports
        them.
    swaps : int
        Exchanges made.
    passes : int
        Exchange passes.
    """

    indices: np.ndarray
    criterion: str
    value: float
    min_singular: float
    condition: float
    upper_bound: float | None
    meets_condition: bool
    indices_own: ObservabilityIndices
    swaps: int
    passes: int

    @property
    def bound_ratio(self) -> float | None:
        """Chosen minimum singular value as a fraction of the certified bound (1 proves the
        set optimal); None without a positive bound."""
        if self.upper_bound is None or self.upper_bound <= 0:
            return None
        return self.min_singular / self.upper_bound


def _compress(G: np.ndarray) -> np.ndarray:
    """Per-pose blocks (N, 4, n) -> the information factors (N, r, n) with A_k = F_k^T F_k,
    keeping only the rows that carry information (the blocks are nearly rank one). Blocks
    of one row (the noise-whitened information rows) are their own factors: an SVD per
    pose would only return each row again, to rounding and its sign."""
    if G.shape[1] == 1:
        return G if np.any(G) else G[:, :0, :]
    _, s, Vt = np.linalg.svd(G, full_matrices=False)
    F = s[:, :, None] * Vt
    keep = np.flatnonzero(s.max(axis=0) > 1e-12 * s.max())
    return F[:, keep, :]


#: above this many pair products (n (n + 1) / 2 per row of F), quadratic forms are
#: evaluated as ``a^T (Z a)`` instead (memory)
_PAIRS_MAX = 8_000_000


class _Quadratic:
    """``<Z, A_k> = sum_r F_kr^T Z F_kr`` for every candidate k at once, for many symmetric Z.

    F: (N, r, n) information factors. With n (n + 1) / 2 pair products ``F_ri F_rj``
    (i <= j) kept row by row, each evaluation is one matrix-vector product over them (the
    Frank-Wolfe iterations and the exchange evaluate thousands of Z on the same rows)."""

    def __init__(self, F: np.ndarray):
        N, r, n = F.shape
        self.N, self.r = N, r
        self.FT = np.ascontiguousarray(F.reshape(N * r, n).T)  # (n, N r)
        iu = np.triu_indices(n)
        if len(iu[0]) * N * r <= _PAIRS_MAX:
            self.iu = iu
            self.twice = np.where(iu[0] == iu[1], 1.0, 2.0)
            self.P = self.FT[iu[0]] * self.FT[iu[1]]  # (n (n + 1) / 2, N r)
        else:
            self.P = None

    def __call__(self, Z: np.ndarray) -> np.ndarray:
        if self.P is not None:
            q = (Z[self.iu] * self.twice) @ self.P
        else:
            q = np.einsum("ir,ir->r", Z @ self.FT, self.FT)
        return q if self.r == 1 else q.reshape(self.N, self.r).sum(axis=1)


def _top(x: np.ndarray, k: int) -> np.ndarray:
    """Indices of the k largest entries of x (in no particular order): those of
    ``np.argpartition(-x, k - 1)[:k]``. Of a long x, only the entries at or above a
    threshold taken from every 16th entry are partitioned (about 2 k of them); if fewer
    than k reach it, all of x is."""
    n = len(x)
    if n >= 2048 and 64 * k <= n:
        sample = x[::16]
        j = len(sample) - max(2, -(-2 * k // 16))
        idx = np.flatnonzero(x >= np.partition(sample, j)[j])
        if len(idx) >= k:
            return idx[np.argpartition(-x[idx], k - 1)[:k]]
    return np.argpartition(-x, k - 1)[:k]


def relaxation_bound(
    F: np.ndarray, k: int, *, iterations: int = 300, w0: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """Frank-Wolfe on the relaxed E-optimal design.

    Parameters
    ----------
    F : ndarray, shape (N, r, n)
        Information factors of N candidates, ``A_k = F_k^T F_k`` (scaled).
    k : int
        Poses to choose.
    iterations : int, default 300
        Frank-Wolfe iterations at most (it stops early once the bound meets the relaxed
        value to 1e-9).
    w0 : ndarray, shape (N,), optional
        Start weights; default ``k / N`` each.

    Returns
    -------
    bound : float
        Upper bound on ``lambda_min(M(S))`` of every k-subset S; it holds for the exact
        matrices F builds.
    weights : ndarray, shape (N,)
        The relaxed weights, in [0, 1], summing to k.

    Notes
    -----
    The information matrix follows the weights' update (a step moves it toward the k
    chosen factors' sum), so an iteration touches every candidate once: for ``<Z, A_k>``.
    """
    return _relax(F, _Quadratic(F), k, iterations, w0)


def _relax(F: np.ndarray, quad: _Quadratic, k: int, iterations: int, w0: np.ndarray | None):
    """:func:`relaxation_bound` with the quadratic forms of F prepared."""
    N, r, n = F.shape
    F2 = F.reshape(N * r, n)
    w = np.full(N, k / N) if w0 is None else w0.astype(float).copy()
    M = (F2 * np.repeat(w, r)[:, None]).T @ F2
    best = np.inf
    gw = np.empty(N)
    for t in range(iterations):
        lam, Q = np.linalg.eigh(M)
        spread = max(lam[-1] - lam[0], 1e-300)
        mu = max(lam[0], 1e-12 * lam[-1]) * 0.02 + 1e-6 * spread / (1 + t)
        pi = np.exp(-(lam - lam[0]) / mu)
        pi /= pi.sum()
        c = quad((Q * pi) @ Q.T)  # <Z, A_k>
        top = _top(c, k)
        best = min(best, float(c[top].sum()))
        if best - lam[0] <= 1e-9 * best:
            break
        # w += g (s - w), s the indicator of top; M the same step toward the top's sum
        g = 2.0 / (t + 3.0)
        wt = w[top]
        np.multiply(w, g, out=gw)
        w -= gw
        w[top] = wt + g * (1.0 - wt)
        Ft = F[top].reshape(-1, n)
        M += g * (Ft.T @ Ft - M)
    return best, w


@dataclass(frozen=True)
class Candidates:
    """Candidate poses prepared for selection.

    Rows of unusable poses are zero, so they are never chosen.

    Attributes
    ----------
    jacobian : ndarray, shape (N, 4, n) or (N, 1, n)
        The design matrix: the loop-residual Jacobian with respect to the free parameters,
        mm^2 per unit (:func:`candidate_jacobian`), or the information rows
        (:func:`ml_candidates`).
    usable : ndarray of bool, shape (N,)
        Not near-singular, and consistent.
    information : ndarray, shape (N, 1, n)
        Each pose's noise-whitened information row: ``u_k^T J_k / s_k`` for the paper's
        residuals (see :func:`loopcal.calibration.residuals.noise_directions`), the pose's
        real information about the parameters per unit voltage noise.
    """

    jacobian: np.ndarray
    usable: np.ndarray
    information: np.ndarray


def candidate_jacobian(
    volts: np.ndarray,
    model: ParameterModel,
    p: np.ndarray,
    *,
    near_singular_mm: float = NEAR_SINGULAR_MM,
) -> Candidates:
    """Prepare N candidate poses for the paper's estimator at the parameter estimate ``p``.

    Parameters
    ----------
    volts : array_like, shape (N, 4)
        LVDT readings of the candidate poses, V.
    model : ParameterModel
        The free set.
    p : array_like, shape (20,)
        Parameter estimate (mm, mm/V).
    near_singular_mm : float, default NEAR_SINGULAR_MM
        Poses whose mirror solutions come closer than this, mm, in any loop, are
        unusable.

    Returns
    -------
    Candidates
        The (N, 4, n) loop-residual Jacobians and the (N, 1, n) whitened information rows.

    Raises
    ------
    InputError, ParameterError
        Bad readings or parameters.
    """
    V = check_volts(volts)
    ref = reference_points(V, p)
    r = loop_residuals(p, V, ref, directions=model.tie_matrix)
    u, s, _ = noise_directions(p, V, ref)
    ok = r.feasible.all(axis=1) & (r.separation.min(axis=1) >= near_singular_mm)
    ok &= np.isfinite(r.jacobian).all(axis=(1, 2)) & (s > 0)
    J = np.where(ok[:, None, None], r.jacobian, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        info = np.where(ok[:, None], (u[:, None, :] @ J)[:, 0] / s[:, None], 0.0)
    return Candidates(J, ok, info[:, None, :])


def ml_candidates(
    volts: np.ndarray,
    model: ParameterModel,
    p: np.ndarray,
    *,
    scans_per_pose: np.ndarray | None = None,
) -> Candidates:
    """Prepare N candidate poses for the maximum-likelihood estimator at the estimate ``p``.

    Each pose's information about the free parameters once its rotation is eliminated is
    rank one (:func:`loopcal.calibration.implicit.weighted_information`); its row, per unit
    noise of one scan (weighted by sqrt(scans_per_pose)), is both the pose's Jacobian and
    its information.

    Parameters
    ----------
    volts, model, p
        As for :func:`candidate_jacobian`: the readings (N, 4), V; the free set; the
        estimate (20,), mm and mm/V.
    scans_per_pose : array_like, shape (N,), optional
        Scans averaged into each pose; default one each.

    Returns
    -------
    Candidates
        ``jacobian`` and ``information`` both the (N, 1, n) information rows. Poses whose
        rotation the lengths do not determine are unusable (rows of zeros).

    Raises
    ------
    InputError, ParameterError
        Bad readings, scan counts or parameters.
    """
    V = check_volts(volts)
    w = implicit.pose_weights(len(V), None, scans_per_pose)
    R, ok = implicit.start_rotations(V, p)
    a = implicit.weighted_information(R, p, model.tie_matrix, w)
    ok &= np.isfinite(a).all(axis=1)
    a = np.where(ok[:, None], a, 0.0)[:, None, :]
    return Candidates(a, ok, a)


def select_poses(
    J: np.ndarray,
    k: int,
    *,
    criterion: str = "min_singular",
    max_condition: float = CONDITION_OK,
    scales: np.ndarray | None = None,
    certify: bool = True,
    shortlist: int = 48,
    max_passes: int = 20,
    information: np.ndarray | None = None,
) -> Selection:
    """Choose k of N candidate poses that best identify the free parameters.

    Parameters
    ----------
    J : array_like, shape (N, r, n) or (4 N, n)
        The candidates' Jacobian: the paper's (N, 4, n) loop-residual Jacobian, or the
        (N, 1, n) information rows of the maximum-likelihood model (:func:`ml_candidates`).
    k : int
        Poses to choose, ``n <= k <= N``.
    criterion : str, default "min_singular"
        One of :data:`CRITERIA` (maximise min_singular, volume, noise_amplification;
        minimise condition, a_optimality).
    max_condition : float, default CONDITION_OK
        Bound on the condition number of the chosen set (pool scaling).
    scales : array_like, shape (n,), optional
        ``diag(H)``; default the pool's own column scaling (of ``information`` if given).
    certify : bool, default True
        Compute the certified upper bound (300 relaxation iterations instead of 60; they
        also seed the exchange).
    shortlist : int, default 48
        Candidates evaluated exactly per exchange position, ranked by first-order gain.
    max_passes : int, default 20
        Exchange passes at most.
    information : array_like, shape (N, r, n), optional
        Per-pose information factors to design on instead of J's own blocks, typically
        :attr:`Candidates.information` (noise-whitened), which keeps the choice away from
        near-singular poses whose large Jacobian rows are mostly amplified noise. The
        paper's indices of the chosen set (``indices_own``) always come from J.

    Returns
    -------
    Selection

    Raises
    ------
    InputError
        An unknown criterion, k outside ``n..N``, a non-finite J, or ``information`` of
        the wrong shape.
    UnobservableError
        If a column of the pool is zero (and ``scales`` is not given).
    """
    rows, N = as_rows(J)
    n = rows.shape[1]
    own_blocks = rows.reshape(N, -1, n)
    if criterion not in CRITERIA:
        raise InputError(f"unknown criterion {criterion!r}; choose one of {', '.join(CRITERIA)}")
    if not (n <= k <= N):
        raise InputError(f"cannot choose {k} poses from {N} candidates for {n} free parameters")
    if not np.all(np.isfinite(rows)):
        raise InputError("the candidates' Jacobian contains NaN (near-singular poses?)")
    if information is None:
        blocks = own_blocks
    else:
        blocks = np.asarray(information, dtype=float)
        if blocks.ndim != 3 or blocks.shape[0] != N or blocks.shape[2] != n:
            raise InputError(f"information must have shape ({N}, r, {n}), got {blocks.shape}")
    h = column_scales(blocks) if scales is None else np.asarray(scales, dtype=float)
    F = _compress(blocks * h)
    quad = _Quadratic(F)

    lam_bound, w = _relax(F, quad, k, 300 if certify else 60, None)
    bound = float(np.sqrt(max(lam_bound, 0.0))) if certify else None
    chosen = np.sort(np.argpartition(-w, k - 1)[:k])
    in_set = np.zeros(N, dtype=bool)
    in_set[chosen] = True

    def info(idx: np.ndarray) -> np.ndarray:  # information matrix of a set, sum of F_k^T F_k
        return np.einsum("kri,krj->ij", F[idx], F[idx])

    M = info(chosen)
    lam = np.linalg.eigvalsh(M)
    cur = float(_criterion_value(lam, criterion, k))
    cond_ok = bool(_condition(lam) <= max_condition)
    swaps = 0
    passes = 0
    short = min(shortlist, N - k)  # candidates outside the set
    # positions tried in a row without a swap: once every position has been tried against
    # the current set, the rest of the pass would repeat those very trials and stop
    unchanged = 0
    while short > 0 and passes < max_passes:
        passes += 1
        improved = False
        for pos in range(k):
            if unchanged >= k:
                break
            unchanged += 1
            i = chosen[pos]
            B = M - F[i].T @ F[i]
            lb, Qb = np.linalg.eigh(B)
            # first-order gain of adding candidate j, weighted towards the weak directions
            scale = max(lb[0], 1e-12 * max(lb[-1], 1e-300))
            wts = np.exp(-(lb - lb[0]) / (0.5 * scale + 1e-300))
            score = quad((Qb * wts) @ Qb.T)
            score[in_set] = -np.inf
            cand = _top(score, short)
            trial = B[None] + np.einsum("kri,krj->kij", F[cand], F[cand])
            lt = np.linalg.eigvalsh(trial)
            vals = _criterion_value(lt, criterion, k)
            conds = _condition(lt)
            if cond_ok:
                vals = np.where(conds <= max_condition, vals, -np.inf)
                b = int(np.argmax(vals))
                better = vals[b] > cur + 1e-12 * abs(cur)
            else:  # first get within the bound: take the swap that lowers the condition most
                b = int(np.argmin(conds))
                better = conds[b] < _condition(lam) * (1 - 1e-12)
            if better:
                j = int(cand[b])
                in_set[i], in_set[j] = False, True
                chosen[pos] = j
                M = trial[b]
                lam = lt[b]
                cur = float(_criterion_value(lam, criterion, k))
                cond_ok = bool(_condition(lam) <= max_condition)
                swaps += 1
                improved = True
                unchanged = 0
        if not improved:
            break
    chosen = np.sort(chosen)
    lam = np.linalg.eigvalsh(info(chosen))
    value = float(_criterion_value(lam, criterion, k))
    if criterion in ("condition", "a_optimality"):
        value = -value
    s = np.sqrt(np.maximum(lam[::-1], 0.0))
    own_rows = own_blocks[chosen].reshape(-1, n)
    own = ObservabilityIndices(
        np.linalg.svd(own_rows * column_scales(own_blocks[chosen]), compute_uv=False), k
    )
    return Selection(
        indices=chosen,
        criterion=criterion,
        value=value,
        min_singular=float(s[-1]),
        condition=float(s[0] / s[-1]) if s[-1] > 0 else float("inf"),
        upper_bound=bound,
        meets_condition=bool(s[-1] > 0 and s[0] / s[-1] <= max_condition),
        indices_own=own,
        swaps=swaps,
        passes=passes,
    )
