"""Pose selection against independent references and properties (issue #21): the chosen
indices recomputed from the singular values of the chosen scaled rows (np.linalg.svd), the
certified bound against every subset of a small pool (brute force), the exchange's result
against every single swap (brute force), the relaxation against weak duality. Any correct
implementation passes these, whatever its arithmetic; none is a copy of former code.

Definitions (calibration/selection.py): pose k contributes ``A_k = G_k^T G_k`` to
``M(S) = sum_{k in S} A_k``, with ``G_k`` its block of the design rows (the information
rows when given, else the Jacobian's) scaled by one column scaling ``H`` for the whole pool,
``diag(H) = sqrt(N) / ||column||`` over all the pool's rows.
"""

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopcal.calibration.parameters import NOMINAL, PAPER7
from loopcal.calibration.selection import (
    CRITERIA,
    candidate_jacobian,
    ml_candidates,
    relaxation_bound,
    select_poses,
)
from loopcal.calibration.simulate import simulate_poses
from tests.support.fuzz import examples

# A bound and the value it bounds come from different computations (eigenvalues of a sum,
# singular values of a stack), exact to rounding of the largest eigenvalue's size: relative
# to lambda_min that is up to the condition number times eps (measured: 1.4e-12).
ROUNDING = 1e-9

#: larger is better for these; condition and a_optimality are reported as smaller-better
MAXIMISED = ("min_singular", "volume", "noise_amplification")


def pool_scale(blocks: np.ndarray) -> np.ndarray:
    """diag(H) of a pool of blocks (N, r, n)."""
    rows = blocks.reshape(-1, blocks.shape[-1])
    return np.sqrt(len(blocks)) / np.linalg.norm(rows, axis=0)


def indices_from_singular_values(s: np.ndarray, k: int) -> dict[str, float]:
    """The criteria of a set of k poses from the singular values s (descending) of its
    scaled rows (docs/model.md section 7)."""
    return {
        "min_singular": s[-1],
        "condition": s[0] / s[-1],
        "volume": np.exp(np.mean(np.log(s))) / np.sqrt(k),
        "noise_amplification": s[-1] ** 2 / s[0],
        "a_optimality": np.sum(1.0 / s**2),
    }


def goodness(lam: np.ndarray, criterion: str, k: int) -> np.ndarray:
    """The criterion, larger better, of information matrices with eigenvalues lam (..., n)
    ascending (their square roots are the scaled rows' singular values)."""
    s = np.sqrt(np.maximum(lam, 0.0))[..., ::-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        value = {
            "min_singular": lambda: s[..., -1],
            "condition": lambda: s[..., 0] / s[..., -1],
            "volume": lambda: np.exp(np.mean(np.log(s), axis=-1)) / np.sqrt(k),
            "noise_amplification": lambda: s[..., -1] ** 2 / s[..., 0],
            "a_optimality": lambda: np.sum(1.0 / s**2, axis=-1),
        }[criterion]()
    return value if criterion in MAXIMISED else -value


def condition_of(lam: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.maximum(lam[..., -1], 0) / np.maximum(lam[..., 0], 0))


def design_blocks(c, info: bool) -> np.ndarray:
    return c.information if info else c.jacobian


def check_selection(sel, J, k, *, information=None, criterion="min_singular",
                    max_condition=1000.0, scales=None, certify=True):  # fmt: skip
    """What a Selection says about itself, recomputed from the rows it names."""
    N, n = len(J), J.shape[-1]
    blocks = J if information is None else information
    h = pool_scale(blocks) if scales is None else scales
    idx = sel.indices
    assert idx.shape == (k,) and np.issubdtype(idx.dtype, np.integer)
    assert np.all(np.diff(idx) > 0)  # ascending, so distinct
    assert idx[0] >= 0 and idx[-1] < N
    s = np.linalg.svd((blocks[idx] * h).reshape(-1, n), compute_uv=False)
    want = indices_from_singular_values(s, k)
    assert sel.criterion == criterion
    assert sel.value == pytest.approx(want[criterion], rel=1e-9)
    assert sel.min_singular == pytest.approx(s[-1], rel=1e-9)
    assert sel.condition == pytest.approx(s[0] / s[-1], rel=1e-9)
    assert sel.meets_condition == (sel.condition <= max_condition)
    # the paper's indices of the chosen set: J's own rows, scaled on their own
    own = J[idx]
    s_own = np.linalg.svd((own * pool_scale(own)).reshape(-1, n), compute_uv=False)
    assert np.allclose(sel.indices_own.singular_values, s_own, rtol=1e-9, atol=0)
    assert sel.indices_own.n_poses == k
    if certify:
        assert sel.upper_bound >= sel.min_singular * (1 - ROUNDING)
        assert sel.bound_ratio == pytest.approx(sel.min_singular / sel.upper_bound)
        assert sel.bound_ratio <= 1 + ROUNDING
    else:
        assert sel.upper_bound is None and sel.bound_ratio is None
    assert sel.swaps >= 0 and sel.passes >= 0


def check_no_swap_improves(sel, blocks, k, *, criterion="min_singular",
                           max_condition=np.inf, scales=None):  # fmt: skip
    """Every swap of one chosen pose for one outside, by brute force: none improves the
    criterion among those within the condition bound; if the set is not within it, none
    lowers the condition."""
    h = pool_scale(blocks) if scales is None else scales
    G = blocks * h
    A = np.einsum("kri,krj->kij", G, G)
    chosen = sel.indices
    outside = np.setdiff1d(np.arange(len(G)), chosen)
    M = A[chosen].sum(axis=0)
    lam = np.linalg.eigvalsh(M)
    trial = M - A[chosen][:, None] + A[outside][None, :]  # (k, N - k, n, n)
    lt = np.linalg.eigvalsh(trial)
    cond = condition_of(lt)
    if condition_of(lam) <= max_condition:
        now = float(goodness(lam, criterion, k))
        vals = np.where(cond <= max_condition, goodness(lt, criterion, k), -np.inf)
        assert vals.max() <= now + 1e-9 * abs(now), (vals.max(), now)
    else:
        assert cond.min() >= condition_of(lam) * (1 - 1e-9)


# --- small pools: every subset, every swap ------------------------------------------------


@pytest.fixture(scope="module")
def small_pools():
    out = {}
    for seed in (3, 4):
        ps = simulate_poses(12, seed=seed, noise_volts=0.04)
        c = candidate_jacobian(ps.volts, PAPER7, NOMINAL)
        out[f"paper-{seed}"] = (c.jacobian, None)
        out[f"paper-info-{seed}"] = (c.jacobian, c.information)
        m = ml_candidates(ps.volts, PAPER7, NOMINAL)
        out[f"ml-{seed}"] = (m.jacobian, m.information)
    return out


def every_subset(blocks, h, k):
    """(C(N, k), k) every k-subset and (C(N, k), n) their information matrices' eigenvalues."""
    subsets = np.array(list(itertools.combinations(range(len(blocks)), k)))
    G = blocks * h
    A = np.einsum("kri,krj->kij", G, G)
    return subsets, np.linalg.eigvalsh(A[subsets].sum(axis=1))


SMALL = [f"{kind}-{seed}" for seed in (3, 4) for kind in ("paper", "paper-info", "ml")]


@pytest.mark.parametrize("pool", SMALL)
@pytest.mark.parametrize("k", [7, 10])
def test_every_subset_below_the_bound_and_no_swap_improves(small_pools, pool, k):
    J, information = small_pools[pool]
    blocks = J if information is None else information
    h = pool_scale(blocks)
    subsets, lam = every_subset(blocks, h, k)
    best = np.sqrt(np.maximum(lam[:, 0], 0)).max()
    sel = select_poses(J, k, information=information, max_condition=np.inf)
    check_selection(sel, J, k, information=information, max_condition=np.inf)
    assert sel.upper_bound >= best * (1 - ROUNDING)
    assert sel.value <= best * (1 + 1e-9)  # no set beats the best of all
    check_no_swap_improves(sel, blocks, k)
    # the relaxation on these factors (A_k = G_k^T G_k): a bound on lambda_min of each
    bound, w = relaxation_bound(blocks * h, k)
    assert bound >= lam[:, 0].max() * (1 - ROUNDING)
    assert np.all(w >= -1e-12) and np.all(w <= 1 + 1e-12)
    assert w.sum() == pytest.approx(k, rel=1e-12)
    relaxed = np.linalg.eigvalsh(np.einsum("k,kri,krj->ij", w, blocks * h, blocks * h))[0]
    assert relaxed <= bound * (1 + ROUNDING)  # weak duality: the weights' value is below it
    assert relaxed >= lam[:, 0].max() * (1 - 0.1)  # and the relaxation was nearly solved


@pytest.mark.parametrize("criterion", CRITERIA)
def test_every_criterion_is_locally_optimal(small_pools, criterion):
    for pool in ("paper-3", "ml-4"):
        J, information = small_pools[pool]
        blocks = J if information is None else information
        for k in (7, 9):
            sel = select_poses(J, k, criterion=criterion, information=information,
                               max_condition=np.inf, certify=False)  # fmt: skip
            check_selection(sel, J, k, information=information, criterion=criterion,
                            max_condition=np.inf, certify=False)  # fmt: skip
            check_no_swap_improves(sel, blocks, k, criterion=criterion)


def test_condition_bound_in_the_exchange(small_pools):
    J, _ = small_pools["paper-4"]
    free = select_poses(J, 8, max_condition=np.inf)
    for bound in (1.2 * free.condition, 0.9 * free.condition, 1.0):
        sel = select_poses(J, 8, max_condition=bound, max_passes=1000)
        check_selection(sel, J, 8, max_condition=bound)
        check_no_swap_improves(sel, J, 8, max_condition=bound)
    assert select_poses(J, 8, max_condition=0.9 * free.condition).condition < free.condition
    assert not select_poses(J, 8, max_condition=1.0).meets_condition


def test_every_pose_and_given_scales(small_pools):
    J, information = small_pools["ml-3"]
    sel = select_poses(J, 12, information=information)  # k = N: all of them
    assert np.array_equal(sel.indices, np.arange(12))
    check_selection(sel, J, 12, information=information)
    h = pool_scale(information) * np.linspace(0.5, 2.0, information.shape[-1])
    sel = select_poses(J, 8, information=information, scales=h, max_condition=np.inf)
    check_selection(sel, J, 8, information=information, scales=h, max_condition=np.inf)
    check_no_swap_improves(sel, information, 8, scales=h)
    subsets, lam = every_subset(information, h, 8)
    assert sel.upper_bound >= np.sqrt(lam[:, 0].max()) * (1 - ROUNDING)


def test_meets_condition_up_to_the_bound(small_pools):
    J, information = small_pools["ml-4"]
    n = J.shape[-1]
    s = np.linalg.svd((information * pool_scale(information)).reshape(-1, n), compute_uv=False)
    everything = s[0] / s[-1]  # of all 12: the only choice of 12
    for bound, meets in ((everything * (1 + 1e-9), True), (everything * (1 - 1e-9), False)):
        sel = select_poses(J, 12, information=information, max_condition=bound)
        check_selection(sel, J, 12, information=information, max_condition=bound)
        assert sel.meets_condition is meets


@st.composite
def synthetic_pools(draw):
    """Factors of N poses (r rows each, n parameters) with entries of spread size."""
    n = draw(st.integers(1, 4))
    N = draw(st.integers(n + 1, 10))
    k = draw(st.integers(n, N - 1))
    r = draw(st.integers(1, 3))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    G = rng.normal(size=(N, r, n)) * rng.uniform(0.1, 10.0, (N, 1, 1))
    return G, k


@pytest.mark.slow
@settings(max_examples=examples(60), deadline=None, derandomize=True, database=None)
@given(synthetic_pools(), st.sampled_from(CRITERIA))
def test_random_pools_every_subset_and_every_swap(pool, criterion):
    G, k = pool
    certify = criterion == "min_singular"
    sel = select_poses(G, k, criterion=criterion, max_condition=np.inf, certify=certify)
    check_selection(sel, G, k, criterion=criterion, max_condition=np.inf, certify=certify)
    check_no_swap_improves(sel, G, k, criterion=criterion)
    if certify:
        _, lam = every_subset(G, pool_scale(G), k)
        assert sel.upper_bound >= np.sqrt(np.maximum(lam[:, 0], 0).max()) * (1 - ROUNDING)


# --- realistic pools ----------------------------------------------------------------------


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
def test_selections_of_realistic_pools(pools, pool, k, kw, info):
    c = pools[pool]
    information = c.information if info else None
    sel = select_poses(c.jacobian, k, information=information, **kw)
    check_selection(sel, c.jacobian, k, information=information, **kw)
    assert c.usable[sel.indices].all()  # never a near-singular or inconsistent pose
    if sel.upper_bound is not None:
        # a bound for random subsets too, and close to the chosen set's value
        blocks = design_blocks(c, info)
        h = pool_scale(blocks)
        rng = np.random.default_rng(k)
        for _ in range(30):
            idx = rng.choice(len(blocks), k, replace=False)
            s = np.linalg.svd((blocks[idx] * h).reshape(-1, blocks.shape[-1]), compute_uv=False)
            assert s[-1] <= sel.upper_bound * (1 + ROUNDING)
        assert sel.bound_ratio > 0.9


@pytest.mark.parametrize(("pool", "info"), [("ml-11", True), ("paper-5", False)])
def test_the_same_input_gives_the_same_selection(pools, pool, info):
    c = pools[pool]
    information = c.information if info else None
    a, b = (select_poses(c.jacobian, 50, information=information) for _ in range(2))
    assert np.array_equal(a.indices, b.indices)
    assert (a.value, a.upper_bound, a.swaps, a.passes) == (
        b.value, b.upper_bound, b.swaps, b.passes)  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize(
    ("pool", "k", "criterion", "info", "bound"),
    [
        ("ml-5", 30, "min_singular", True, np.inf),
        ("paper-5", 30, "min_singular", False, np.inf),
        ("paper-5", 30, "volume", False, np.inf),
        ("paper-5", 30, "min_singular", False, 5.0),  # out of reach: the lowest condition
        ("ml-5", 30, "min_singular", True, 6.0),
    ],
)
def test_exchange_over_every_candidate_is_locally_optimal(pools, pool, k, criterion, info, bound):
    """With the shortlist as long as the pool, every swap is tried exactly: none of the
    k (N - k) swaps improves the result."""
    c = pools[pool]
    information = c.information if info else None
    sel = select_poses(c.jacobian, k, information=information, criterion=criterion,
                       max_condition=bound, shortlist=len(c.jacobian), max_passes=1000,
                       certify=False)  # fmt: skip
    check_selection(sel, c.jacobian, k, information=information, criterion=criterion,
                    max_condition=bound, certify=False)  # fmt: skip
    check_no_swap_improves(sel, design_blocks(c, info), k, criterion=criterion, max_condition=bound)
    if bound == 5.0:
        assert not sel.meets_condition


def test_more_exchange_passes_never_make_it_worse(pools):
    c = pools["paper-5"]
    values, swaps = [], []
    for passes in (0, 1, 2, 20):
        sel = select_poses(c.jacobian, 40, information=c.information, max_condition=np.inf,
                           max_passes=passes, certify=False)  # fmt: skip
        check_selection(sel, c.jacobian, 40, information=c.information, max_condition=np.inf,
                        certify=False)  # fmt: skip
        values.append(sel.value)
        swaps.append(sel.swaps)
        assert sel.passes <= passes
    assert swaps[0] == 0 and swaps[-1] > 0
    assert all(b >= a for a, b in itertools.pairwise(values))
    assert all(b >= a for a, b in itertools.pairwise(swaps))


@pytest.mark.slow
def test_the_same_information_in_other_factors_gives_the_same_choice(pools):
    """Only A_k = G_k^T G_k matters: each pose's four rows turned by an orthogonal 4x4
    (column norms kept, so the scaling too), or padded with rows of zeros, change nothing
    but rounding."""
    c = pools["paper-5"]
    J = c.jacobian
    rng = np.random.default_rng(2)
    Q = np.linalg.qr(rng.normal(size=(len(J), 4, 4)))[0]
    sel = select_poses(J, 40)
    turned = select_poses(Q @ J, 40)
    assert np.array_equal(turned.indices, sel.indices)
    assert turned.value == pytest.approx(sel.value, rel=1e-9)
    assert turned.upper_bound == pytest.approx(sel.upper_bound, rel=1e-9)
    a = c.information * pool_scale(c.information)
    for k in (7, 50):
        b0, w0 = relaxation_bound(a, k)
        b1, w1 = relaxation_bound(np.concatenate([a, np.zeros_like(a)], axis=1), k)
        assert b1 == pytest.approx(b0, rel=1e-9)
        assert np.allclose(w1, w0, rtol=0, atol=1e-9)
    # many rows of many parameters (the forms may then be evaluated another way): a few
    # iterations
    a = rng.normal(size=(1000, 1, 20)) * rng.uniform(0.1, 3.0, (1000, 1, 1))
    padded = np.concatenate([a, np.zeros((1000, 39, 20))], axis=1)
    for k in (40,):
        b0, w0 = relaxation_bound(a, k, iterations=8)
        b1, w1 = relaxation_bound(padded, k, iterations=8)
        assert b1 == pytest.approx(b0, rel=1e-9)
        assert np.allclose(w1, w0, rtol=0, atol=1e-9)


def test_relaxation_of_a_large_pool_is_a_near_certificate(pools):
    """Frank-Wolfe's bound against the value of its own weights (weak duality) and against
    subsets, on the largest pool (N = 6000)."""
    a = pools["ml-11"].information
    F = a * pool_scale(a)
    rng = np.random.default_rng(0)
    for k in (7, 50, 300):
        bound, w = relaxation_bound(F, k)
        assert np.all(w >= -1e-12) and np.all(w <= 1 + 1e-12)
        assert w.sum() == pytest.approx(k, rel=1e-12)
        relaxed = np.linalg.eigvalsh(np.einsum("k,kri,krj->ij", w, F, F))[0]
        assert relaxed <= bound * (1 + ROUNDING) and relaxed >= 0.9 * bound
        top = np.argsort(-w)[:k]  # the rounded weights: a subset, below the bound
        for idx in [top, *(rng.choice(len(F), k, replace=False) for _ in range(20))]:
            lam = np.linalg.eigvalsh(np.einsum("kri,krj->ij", F[idx], F[idx]))[0]
            assert lam <= bound * (1 + ROUNDING)
