"""Pose selection and the certified bound."""

import numpy as np
import pytest

from loopcal.calibration.errors import InputError
from loopcal.calibration.observability import column_scales, observability_indices
from loopcal.calibration.parameters import NOMINAL, PAPER7
from loopcal.calibration.selection import candidate_jacobian, select_poses
from loopcal.calibration.simulate import simulate_poses


@pytest.fixture(scope="module")
def pool():
    ps = simulate_poses(2000, seed=8)
    c = candidate_jacobian(ps.volts, PAPER7, NOMINAL)
    return c.jacobian, c.usable


def test_selection_near_certified_bound_and_far_above_random(pool):
    J, ok = pool
    sel = select_poses(J, 50)
    assert len(sel.indices) == 50 and len(set(sel.indices)) == 50
    assert ok[sel.indices].all()  # never a near-singular pose
    assert sel.min_singular <= sel.upper_bound * (1 + 1e-9)  # the bound is a bound
    assert sel.bound_ratio > 0.9
    h = column_scales(J)
    rng = np.random.default_rng(0)
    random = [
        observability_indices(J[rng.choice(np.flatnonzero(ok), 50, replace=False)], h).min_singular
        for _ in range(20)
    ]
    assert sel.min_singular > 2 * np.max(random)
    # reported value is the chosen set's own index on the pool scale
    assert sel.min_singular == pytest.approx(observability_indices(J[sel.indices], h).min_singular)


def test_bound_holds_for_random_subsets_too(pool):
    J, ok = pool
    sel = select_poses(J, 20)
    h = column_scales(J)
    rng = np.random.default_rng(1)
    for _ in range(50):
        idx = rng.choice(len(J), 20, replace=False)
        assert observability_indices(J[idx], h).min_singular <= sel.upper_bound * (1 + 1e-9)


def test_condition_bound_is_respected(pool):
    J, _ = pool
    free = select_poses(J, 30, max_condition=1e9)
    capped = select_poses(J, 30, max_condition=0.99 * free.condition)
    assert capped.meets_condition
    assert capped.condition <= 0.99 * free.condition
    impossible = select_poses(J, 30, max_condition=1.0)
    assert not impossible.meets_condition


@pytest.mark.parametrize(
    "criterion", ["volume", "a_optimality", "condition", "noise_amplification"]
)
def test_other_criteria_beat_random(pool, criterion):
    J, ok = pool
    sel = select_poses(J, 40, criterion=criterion, certify=False)
    h = column_scales(J)
    rng = np.random.default_rng(2)
    rnd = observability_indices(J[rng.choice(np.flatnonzero(ok), 40, replace=False)], h)
    mine = observability_indices(J[sel.indices], h)
    better = {
        "volume": mine.volume > rnd.volume,
        "a_optimality": mine.a_optimality < rnd.a_optimality,
        "condition": mine.condition < rnd.condition,
        "noise_amplification": mine.noise_amplification > rnd.noise_amplification,
    }
    assert better[criterion]


def test_bad_selection_requests(pool):
    J, _ = pool
    with pytest.raises(InputError, match="cannot choose 3 poses"):
        select_poses(J, 3)
    with pytest.raises(InputError, match="unknown criterion"):
        select_poses(J, 20, criterion="best")
