"""The still-pose search against the straightforward version it replaced (issue #16):
every window's peak-to-peak by a (n, 4, window) view, a Python loop over the stretches to
split them. The fast one must find the same poses, bit for bit."""

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from loopcal.calibration.poses import (
    _BLOCK,
    _covered,
    _split,
    _window_all,
    _window_spread,
    running_sums_at,
    still_poses,
)
from loopcal.calibration.simulate import quantize_volts


def reference_still_poses(V, *, window=10, band_volts=0.25, max_scans=None, valid=None):
    """calibration.poses.still_poses as it was before issue #16 (ranges only: the means
    and spreads are computed the same way from them)."""
    n = len(V)
    ok = np.ones(n, dtype=bool) if valid is None else valid
    if n < window:
        return np.zeros((0, 2), dtype=int)
    win = sliding_window_view(V, window, axis=0)
    still_win = (np.ptp(win, axis=2).max(axis=1) <= band_volts) & sliding_window_view(
        ok, window
    ).all(axis=1)
    cover = np.zeros(n + 1, dtype=int)
    starts = np.flatnonzero(still_win)
    np.add.at(cover, starts, 1)
    np.add.at(cover, starts + window, -1)
    still = np.cumsum(cover[:-1]) > 0
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(int), [0]])))
    ranges = edges.reshape(-1, 2)
    if max_scans is not None:
        pieces = []
        for a, b in ranges:
            cuts = list(range(a, b, max_scans)) + [b]
            pieces += [(c0, c1) for c0, c1 in zip(cuts[:-1], cuts[1:], strict=True)
                       if c1 - c0 >= window]  # fmt: skip
        ranges = np.array(pieces, dtype=int).reshape(-1, 2)
    return ranges


def reference_means(V, ranges):
    """The stretches' means and standard deviations as they were computed before."""
    csum = np.concatenate([np.zeros((1, 4)), np.cumsum(V, axis=0)])
    csq = np.concatenate([np.zeros((1, 4)), np.cumsum(V * V, axis=0)])
    cnt = (ranges[:, 1] - ranges[:, 0])[:, None]
    mean = (csum[ranges[:, 1]] - csum[ranges[:, 0]]) / cnt
    var = np.maximum((csq[ranges[:, 1]] - csq[ranges[:, 0]]) / cnt - mean**2, 0.0)
    return mean, np.sqrt(var)


def hand_moves(rng, n, noise=0.04):
    """Readings of a plate moved and held still in turn, quantised like the DAQ's."""
    V = np.empty((n, 4))
    i, level = 0, rng.uniform(-8, 8, 4)
    while i < n:
        hold = int(rng.integers(5, 160))
        V[i : i + hold] = level
        i += hold
        move = int(rng.integers(3, 40))
        target = rng.uniform(-8, 8, 4)
        V[i : i + move] = np.linspace(level, target, move + 2)[1:-1][: n - i]
        i, level = i + move, target
    V += rng.normal(0, noise, V.shape)
    return quantize_volts(V)[1]


@pytest.mark.parametrize("window", [2, 3, 4, 7, 8, 10, 16, 25])
def test_window_spread_is_the_peak_to_peak_of_every_window(window):
    rng = np.random.default_rng(window)
    for n in (window, window + 1, 1000, (1 << 14) + window - 1, (1 << 14) + window, 40_000):
        V = rng.normal(0, 1, (n, 4))
        expected = np.ptp(sliding_window_view(V, window, axis=0), axis=2).max(axis=1)
        assert np.array_equal(_window_spread(V, window), expected)


def test_running_sums_are_cumsums_bit_for_bit():
    rng = np.random.default_rng(5)
    for n in (1, 5, _BLOCK - 1, _BLOCK, _BLOCK + 1, 3 * _BLOCK + 17):
        X = rng.normal(3.0, 2.0, (n, 3)) * 10.0 ** rng.integers(-3, 4, (n, 1))
        S = np.concatenate([np.zeros((1, 3)), np.cumsum(X, axis=0)])
        at = np.concatenate([[0, n, n, 0], rng.integers(0, n + 1, 500)])  # any order, repeats
        got = running_sums_at(lambda a, b: X[a:b].copy(), n, at)  # noqa: B023
        assert np.array_equal(got, S[at])
        early = at[at <= n // 3]  # the blocks past the last index are not read
        read = []
        got = running_sums_at(lambda a, b: read.append(b) or X[a:b].copy(), n, early)  # noqa: B023
        assert np.array_equal(got, S[early])
        assert max(read, default=0) <= max(n // 3 + _BLOCK, _BLOCK)
    X = np.ones((10, 2))
    assert np.array_equal(running_sums_at(lambda a, b: X[a:b].copy(), 10, [0, 0]), np.zeros((2, 2)))
    assert running_sums_at(lambda a, b: X[a:b].copy(), 0, [0]).shape == (1, 2)


def test_window_all_and_split():
    rng = np.random.default_rng(3)
    ok = rng.random(5000) > 0.01
    for window in (2, 10, 33):
        assert np.array_equal(_window_all(ok, window), sliding_window_view(ok, window).all(axis=1))
        starts = rng.random(len(ok) - window + 1) < 0.01
        cover = np.zeros(len(ok) + 1, dtype=int)
        np.add.at(cover, np.flatnonzero(starts), 1)
        np.add.at(cover, np.flatnonzero(starts) + window, -1)
        assert np.array_equal(_covered(starts, window), np.cumsum(cover[:-1]) > 0)
    lengths = rng.integers(10, 400, 300)
    gaps = rng.integers(1, 50, 300)
    a = np.cumsum(gaps + np.concatenate([[0], lengths[:-1]]))
    ranges = np.stack([a, a + lengths], axis=1)
    for max_scans, window in ((100, 10), (10, 10), (37, 5)):
        expected = []
        for x, y in ranges:
            cuts = list(range(x, y, max_scans)) + [y]
            pairs = zip(cuts[:-1], cuts[1:], strict=True)
            expected += [(c, d) for c, d in pairs if d - c >= window]
        assert np.array_equal(_split(ranges, max_scans, window), np.array(expected))
    assert _split(np.zeros((0, 2), dtype=int), 100, 10).shape == (0, 2)


@pytest.mark.parametrize("seed", range(6))
def test_same_poses_as_the_reference(seed):
    rng = np.random.default_rng(seed)
    V = hand_moves(rng, 30_000 + 977 * seed)
    valid = rng.random(len(V)) > 0.002
    valid[rng.integers(0, len(V), 5)[:, None] + np.arange(12)] = False  # a few gaps
    for kw in (
        {},
        {"valid": valid},
        {"valid": valid, "max_scans": 100},
        {"window": 16, "band_volts": 0.3, "max_scans": 16},
        {"window": 5, "band_volts": 0.2, "max_scans": 50, "valid": valid},
    ):
        sp = still_poses(V, **kw)
        ref = reference_still_poses(V, **kw)
        assert np.array_equal(sp.ranges, ref)
        assert sp.ranges.dtype == ref.dtype
        assert len(sp) > 50
        mean, spread = reference_means(V, ref)
        assert np.array_equal(sp.volts, mean)
        assert np.array_equal(sp.spread, spread)


def test_edge_cases():
    V = np.zeros((9, 4))
    assert len(still_poses(V)) == 0  # shorter than a window
    assert np.array_equal(still_poses(np.zeros((10, 4))).ranges, [[0, 10]])
    moving = np.outer(np.arange(100.0), np.ones(4))
    assert len(still_poses(moving)) == 0
    assert len(still_poses(np.zeros((100, 4)), valid=np.zeros(100, dtype=bool))) == 0
