"""Single scans as calibration samples: the channel skew taken out, noise that motion does
not inflate, the misfit's averaging and the score test of fixed gains."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopcal.calibration import implicit
from loopcal.calibration.errors import InputError
from loopcal.calibration.identify import identify
from loopcal.calibration.kinematics import inverse_kinematics, lengths_to_volts
from loopcal.calibration.parameters import INDEX, NOMINAL, PAPER7, SL_GAIN
from loopcal.calibration.scans import (
    CHANNEL_SKEW_S,
    averaging_ratio,
    closure_misfit,
    deskew,
    difference_noise,
)
from loopcal.simulator.scenarios import HandMoves
from tests.support.fuzz import examples

RATE = 20.0


def hand_volts(
    seconds: float, seed: int = 3, *, skew: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free readings of a hand-moved plate at 20 Hz: each channel at its own instant
    (skew) or all at the stamp; and the rotations at the stamps."""
    t = np.arange(round(seconds * RATE)) / RATE
    motion = HandMoves(seed, params=NOMINAL, pause_s=(0.2, 0.5))
    R = motion.rotation(t)
    if not skew:
        return lengths_to_volts(inverse_kinematics(R, NOMINAL), NOMINAL), R
    V = np.empty((len(t), 4))
    for i in range(4):
        Ri = motion.rotation(t + i * CHANNEL_SKEW_S)
        V[:, i] = lengths_to_volts(inverse_kinematics(Ri, NOMINAL), NOMINAL)[:, i]
    return V, R


def test_deskew_brings_each_reading_to_the_stamp():
    skewed, _ = hand_volts(60)
    at_stamp, _ = hand_volts(60, skew=False)
    before = np.abs(skewed - at_stamp)[:, 1:].max()
    V, corrected = deskew(skewed, 1 / RATE)
    after = np.abs(V - at_stamp)[1:-1, 1:].max()
    assert corrected.all() and np.array_equal(V[:, 0], skewed[:, 0])  # channel 1 is the stamp
    assert before > 1e-3 and after < before / 20, (before, after)


def test_deskew_never_reaches_across_an_unusable_scan():
    skewed, _ = hand_volts(10)
    valid = np.ones(len(skewed), dtype=bool)
    valid[[49, 51]] = False  # scan 50 is alone between two unusable ones
    V, corrected = deskew(skewed, 1 / RATE, valid=valid)
    rows = np.flatnonzero(valid)
    assert not corrected[rows == 50].any() and corrected[rows != 50].all()
    assert np.array_equal(V[rows == 50][0], skewed[50])  # alone: as it was
    # the scan before an unusable one takes its rate from itself and the one before
    far = skewed.copy()
    far[49:] += 5.0
    W, _ = deskew(far, 1 / RATE, valid=valid, rows=np.arange(48))
    assert np.allclose(W, V[:48])
    # a subset of rows is corrected exactly as it is among all of them
    some = rows[::7]
    S, _ = deskew(skewed, 1 / RATE, valid=valid, rows=some)
    assert np.array_equal(S, V[::7])


def test_difference_noise_is_not_fooled_by_motion():
    V, _ = hand_volts(120)
    rng = np.random.default_rng(1)
    noisy = V + rng.normal(0, 0.04, V.shape)
    est = difference_noise(noisy)
    assert np.all(np.abs(est / 0.04 - 1) < 0.06), est
    naive = np.sqrt(np.mean(np.diff(noisy, axis=0) ** 2, axis=0) / 2)
    assert np.all(naive > 2 * 0.04)  # scan-to-scan differences see the motion


@settings(max_examples=examples(80), deadline=None)
@given(
    n=st.integers(0, 40),
    holes=st.lists(st.integers(0, 39), max_size=6),
    rows=st.one_of(st.none(), st.lists(st.integers(-3, 45), max_size=6)),
    period=st.sampled_from([0.05, 0.0, -1.0, float("nan")]),
)
def test_bad_rows_and_periods_are_refused_in_words(n, holes, rows, period):
    V = np.zeros((n, 4))
    valid = np.ones(n, dtype=bool)
    valid[[h for h in holes if h < n]] = False
    at = None if rows is None else np.array(rows, dtype=np.int64)
    ok_rows = rows is None or all(0 <= r < n and valid[r] for r in rows)
    try:
        out, corrected = deskew(V, period, valid=valid, rows=at)
    except InputError as exc:
        assert "rows" in str(exc) or "period" in str(exc) or "volts" in str(exc).lower()
        assert not (ok_rows and period == 0.05 and n > 0)
    else:
        k = int(valid.sum()) if rows is None else len(rows)
        assert ok_rows and period == 0.05 and out.shape == (k, 4) and corrected.shape == (k,)
        noise = difference_noise(V, valid=valid, rows=at)
        assert noise.shape == (4,) and not np.any(noise > 0)  # zeros or NaN: no noise here
    with pytest.raises(InputError, match="valid"):
        deskew(V, 0.05, valid=np.ones(n + 1, dtype=bool))


def test_averaging_ratio_tells_white_noise_from_a_slow_misfit():
    rng = np.random.default_rng(2)
    white = rng.normal(size=4000)
    r, J = averaging_ratio(white, np.array([0, 1500, 1517]), 20)
    assert J == 75 + 0 + 124 and 0.7 < r < 1.3  # 1500 // 20, the 17-scan run has none
    slow = white + 0.5 * np.sin(np.arange(4000) / 40)
    assert averaging_ratio(slow, None, 20)[0] > 3
    assert np.isnan(averaging_ratio(white[:10], None, 20)[0])
    with pytest.raises(InputError):
        averaging_ratio(white, None, 1)


def _fit(gain_error: float, seed: int):
    V, _ = hand_volts(90, seed)
    rng = np.random.default_rng(seed)
    noisy = V + rng.normal(0, 0.04, V.shape)
    noisy = noisy[np.all(np.abs(noisy) < 9.95, axis=1)]  # the module reads the rail there
    start = NOMINAL.copy()
    start[INDEX["S3"]] *= 1 + gain_error
    ident = identify(noisy, PAPER7, start, method="ml")
    E = np.zeros((20, 4))
    E[np.arange(SL_GAIN.start, SL_GAIN.stop), np.arange(4)] = 1
    test = implicit.score_test(noisy, np.ones_like(noisy), ident.rotations, ident.params,
                               PAPER7.tie_matrix, E)  # fmt: skip
    return ident, noisy, test


@pytest.mark.slow
def test_the_score_test_finds_a_wrong_gain_and_not_a_right_one():
    stats = []
    for seed in (1, 2, 3):
        ident, noisy, t = _fit(0.0, seed)
        stats.append(t.statistic / ident.sigma_volts**2)
        misfit = closure_misfit(noisy, ident.rotations, ident.params)
        assert abs(np.sqrt(np.mean(misfit**2)) / 0.04 - 1) < 0.1
    assert max(stats) < 18.5  # chi-square(4), 99.9 %
    ident, _, t = _fit(0.02, 1)
    assert t.statistic / ident.sigma_volts**2 > 18.5
    # the change it finds is the error, in the right direction (S3 2 % too high)
    j = int(np.argmax(np.abs(t.change) / t.std))
    assert j == 2 and t.change[2] < 0
