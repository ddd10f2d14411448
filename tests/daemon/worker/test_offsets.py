"""The offsets' covariance the upkeep keeps through its fixes: what the offsets held at the
config carry into the ones refitted, as far as their patterns correlate over the motion."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from loopcal.daemon.config.controller import ControllerConfig
from loopcal.daemon.worker.offsets import OFFSETS, config_cov, fixed_cov
from tests.support.fuzz import examples


def config(provenance) -> ControllerConfig:
    return ControllerConfig(None, np.zeros(20), None, (), "", "", provenance)


def test_a_fix_on_motion_that_cannot_tell_the_offsets_apart_takes_in_the_others():
    """Every pose sees the four offsets alike (one pattern): the fixed one is off by
    whatever the three held are off by, and its error is theirs, the other way."""
    H = np.ones((50, 4))
    cov = np.diag([0.01, 0.02, 0.03, 0.04]) ** 2
    out = fixed_cov(cov, H.T @ H, ["d01"], {"d01": 0.005})
    assert np.isclose(out[0, 0], 0.005**2 + 0.02**2 + 0.03**2 + 0.04**2)
    assert np.allclose(np.diag(out)[1:], np.diag(cov)[1:])  # the held ones: as they were
    assert np.allclose(out[0, 1:], -np.diag(cov)[1:])  # anti-correlated: it absorbed them
    assert np.allclose(out, out.T) and np.linalg.eigvalsh(out).min() > -1e-15


def test_a_fix_on_motion_that_tells_the_offsets_apart_is_known_to_its_scans():
    cov = np.diag([0.01, 0.02, 0.03, 0.04]) ** 2
    N = np.diag([4.0, 3.0, 2.0, 1.0]) * 1e4
    out = fixed_cov(cov, N, ["d02", "d04"], {"d02": 0.006, "d04": 0.007})
    assert np.allclose(np.diag(out), [0.01**2, 0.006**2, 0.03**2, 0.007**2])
    assert np.allclose(out - np.diag(np.diag(out)), 0.0)


def test_fixes_in_turn_carry_what_each_left_into_the_next():
    """Two fixes on one-pattern motion: the second takes in the first's error, which had
    taken in the second's offset's own: they cancel in the loop, not in the offsets."""
    N = np.ones((4, 4)) * 100.0
    cov = np.eye(4) * 0.01**2
    once = fixed_cov(cov, N, ["d01"], {"d01": 0.0})
    twice = fixed_cov(once, N, ["d02"], {"d02": 0.0})
    e = np.ones(4)  # the loop sees only the sum of the four offsets' errors
    assert np.isclose(e @ twice @ e, 0.0, atol=1e-12)  # the loops close...
    assert np.sqrt(twice[1, 1]) > 0.01  # ...though d02 is known worse than before


def test_the_config_covariance_is_the_recorded_one_or_the_std_squared():
    cov = [[4e-4, -1e-4, 0, 0], [-1e-4, 4e-4, 0, 0], [0, 0, 1e-4, 0], [0, 0, 0, 1e-4]]
    assert np.allclose(config_cov(config({"offset_cov": cov})), cov)
    std = {n: 0.01 * (i + 1) for i, n in enumerate(OFFSETS)}
    assert np.allclose(config_cov(config({"std": std})), np.diag([0.01, 0.02, 0.03, 0.04]) ** 2)
    assert np.allclose(config_cov(config(None)), np.eye(4) * 0.05**2)
    zero = {"std": {"d01": 0.0, "d02": -0.01, "d03": True, "d04": float("inf")}}
    assert np.allclose(config_cov(config(zero)), np.eye(4) * 0.05**2)  # none of them a std


ELEMENT = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=2), st.booleans()
)
RAW = st.one_of(
    st.none(),
    st.text(max_size=5),
    st.lists(st.floats(allow_nan=True), max_size=5),
    st.lists(st.lists(ELEMENT, max_size=5), max_size=5),
)


@given(RAW)
@settings(max_examples=examples(200), deadline=None)
def test_a_damaged_recorded_covariance_is_never_taken(raw):
    """What a person or a program wrote there, whatever it is: taken only as a whole
    symmetric positive definite (4, 4), else the std squared; never an exception."""
    out = config_cov(config({"offset_cov": raw, "std": {n: 0.02 for n in OFFSETS}}))
    assert out.shape == (4, 4) and np.isfinite(out).all()
    assert np.linalg.eigvalsh(out).min() > 0
