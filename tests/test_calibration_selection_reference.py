"""Pose selection against the straightforward version it replaced (issue #16).

Before, every Frank-Wolfe iteration rebuilt the information matrix from all N candidates,
evaluated ``<Z, A_k>`` through an (N, n) product and partitioned all N values, and the
exchange did the same for every position. Now the matrix follows the weights' update,
``<Z, A_k>`` is one product over the candidates' pair products, the k largest are found
among a few hundred, the exchange stops once every position has been tried against the
current set, and single-row blocks skip the SVD that only returned them. The arithmetic
differs in rounding only: the same poses must be chosen, with the same swaps and passes,
and the same criterion value and certified bound to rounding.
"""

import numpy as np
import pytest

from loopcal.calibration.observability import column_scales
from loopcal.calibration.parameters import NOMINAL, PAPER7
from loopcal.calibration.selection import (
    _compress,
    _criterion_value,
    _Quadratic,
    _top,
    candidate_jacobian,
    ml_candidates,
    relaxation_bound,
    select_poses,
)
from loopcal.calibration.simulate import simulate_poses


def reference_relaxation(F, k, iterations=300):
    N, r, n = F.shape
    F2 = F.reshape(N * r, n)
    w = np.full(N, k / N)
    best = np.inf
    for t in range(iterations):
        M = (F2 * np.repeat(w, r)[:, None]).T @ F2
        lam, Q = np.linalg.eigh(M)
        spread = max(lam[-1] - lam[0], 1e-300)
        mu = max(lam[0], 1e-12 * lam[-1]) * 0.02 + 1e-6 * spread / (1 + t)
        pi = np.exp(-(lam - lam[0]) / mu)
        pi /= pi.sum()
        c = ((F2 @ Q) ** 2 @ pi).reshape(N, r).sum(axis=1)
        top = np.argpartition(-c, k - 1)[:k]
        best = min(best, float(c[top].sum()))
        s = np.zeros(N)
        s[top] = 1.0
        if best - lam[0] <= 1e-9 * best:
            break
        w += 2.0 / (t + 3.0) * (s - w)
    return best, w


def _condition(lam):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.maximum(lam[..., -1], 0) / np.maximum(lam[..., 0], 0))


def reference_select(J, k, *, criterion="min_singular", max_condition=1000.0, certify=True,
                     information=None, shortlist=48, max_passes=20):  # fmt: skip
    """calibration.selection.select_poses before issue #16: (indices, value, bound, swaps,
    passes)."""
    n = J.shape[-1]
    N = len(J)
    blocks = J if information is None else information
    F = _compress(blocks * column_scales(blocks))
    F2 = F.reshape(-1, n)
    lam_bound, w = reference_relaxation(F, k, iterations=300 if certify else 60)
    bound = float(np.sqrt(max(lam_bound, 0.0))) if certify else None
    chosen = np.sort(np.argpartition(-w, k - 1)[:k])
    in_set = np.zeros(N, dtype=bool)
    in_set[chosen] = True
    M = np.einsum("kri,krj->ij", F[chosen], F[chosen])
    lam = np.linalg.eigvalsh(M)
    cur = float(_criterion_value(lam, criterion, k))
    cond_ok = bool(_condition(lam) <= max_condition)
    swaps = passes = 0
    short = min(shortlist, N - k)
    while short > 0 and passes < max_passes:
        passes += 1
        improved = False
        for pos in range(k):
            i = chosen[pos]
            B = M - F[i].T @ F[i]
            lb, Qb = np.linalg.eigh(B)
            scale = max(lb[0], 1e-12 * max(lb[-1], 1e-300))
            wts = np.exp(-(lb - lb[0]) / (0.5 * scale + 1e-300))
            score = ((F2 @ Qb) ** 2 @ wts).reshape(N, -1).sum(axis=1)
            score[in_set] = -np.inf
            cand = np.argpartition(-score, short - 1)[:short]
            trial = B[None] + np.einsum("kri,krj->kij", F[cand], F[cand])
            lt = np.linalg.eigvalsh(trial)
            vals = _criterion_value(lt, criterion, k)
            conds = _condition(lt)
            if cond_ok:
                vals = np.where(conds <= max_condition, vals, -np.inf)
                b = int(np.argmax(vals))
                better = vals[b] > cur + 1e-12 * abs(cur)
            else:
                b = int(np.argmin(conds))
                better = conds[b] < _condition(lam) * (1 - 1e-12)
            if better:
                j = int(cand[b])
                in_set[i], in_set[j] = False, True
                chosen[pos] = j
                M, lam = trial[b], lt[b]
                cur = float(_criterion_value(lam, criterion, k))
                cond_ok = bool(_condition(lam) <= max_condition)
                swaps += 1
                improved = True
        if not improved:
            break
    chosen = np.sort(chosen)
    value = float(_criterion_value(np.linalg.eigvalsh(M), criterion, k))
    return chosen, value, bound, swaps, passes


@pytest.fixture(scope="module")
def pools():
    out = {}
    for seed, N in ((8, 2000), (5, 450), (11, 6000)):
        ps = simulate_poses(N, seed=seed, noise_volts=0.04)
        out[f"paper-{seed}"] = candidate_jacobian(ps.volts, PAPER7, NOMINAL)
        out[f"ml-{seed}"] = ml_candidates(ps.volts, PAPER7, NOMINAL)
    return out


CASES = [
    ("ml-11", 50, {}, True),
    ("ml-8", 50, {}, True),
    ("ml-8", 20, {}, True),
    ("ml-5", 50, {"certify": False}, True),
    ("paper-8", 50, {}, True),
    ("paper-11", 50, {}, True),
    ("paper-5", 50, {}, False),  # the (N, 4, n) Jacobian's own blocks: r = 4
    ("paper-5", 30, {"max_condition": 5.0}, False),
    ("paper-5", 40, {"criterion": "volume", "certify": False}, False),
    ("paper-5", 40, {"criterion": "condition", "certify": False}, False),
    ("paper-8", 40, {"criterion": "a_optimality", "certify": False}, True),
]


@pytest.mark.parametrize(("pool", "k", "kw", "info"), CASES)
def test_same_selection_as_before(pools, pool, k, kw, info):
    c = pools[pool]
    information = c.information if info else None
    sel = select_poses(c.jacobian, k, information=information, **kw)
    idx, value, bound, swaps, passes = reference_select(
        c.jacobian, k, information=information, **kw
    )
    assert np.array_equal(sel.indices, idx)
    assert sel.value == pytest.approx(value if kw.get("criterion") not in (
        "condition", "a_optimality") else -value, rel=1e-13)  # fmt: skip
    assert (sel.swaps, sel.passes) == (swaps, passes)
    if bound is None:
        assert sel.upper_bound is None
    else:
        assert sel.upper_bound == pytest.approx(bound, rel=1e-12)


def test_relaxation_against_reference(pools):
    a = pools["ml-11"].information
    F = _compress(a * column_scales(a))
    for k in (7, 50, 300):
        best, w = relaxation_bound(F, k)
        ref_best, ref_w = reference_relaxation(F, k)
        assert best == pytest.approx(ref_best, rel=1e-12)
        assert np.allclose(w, ref_w, rtol=1e-12, atol=0)


def test_quadratic_forms_and_top():
    rng = np.random.default_rng(4)
    for N, r, n in ((5000, 1, 7), (300, 4, 7), (2000, 2, 20)):
        F = rng.normal(size=(N, r, n))
        A = rng.normal(size=(n, n))
        Z = A @ A.T
        expected = np.einsum("kri,ij,krj->k", F, Z, F)
        quad = _Quadratic(F)
        assert np.allclose(quad(Z), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
        quad.P = None  # the form without pair products (many parameters, many candidates)
        assert np.allclose(quad(Z), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    for n in (10, 3000, 40_000):
        x = rng.normal(size=n)
        x[rng.integers(0, n, n // 10)] = -np.inf  # the chosen set, kept out
        for k in (1, 7, 48)[: 2 if n < 48 else 3]:
            assert set(_top(x, k)) == set(np.argpartition(-x, k - 1)[:k])
    x = np.zeros(40_000)  # a sample that cannot tell: every entry ties
    x[:3] = 1.0
    assert set(_top(x, 3)) == {0, 1, 2}
    assert len(_top(x, 10)) == 10
    x = rng.random(40_000)
    x[::16] += 1.0  # the sample holds the largest: too few reach its threshold, all of x
    assert set(_top(x, 48)) == set(np.argpartition(-x, 47)[:48])
