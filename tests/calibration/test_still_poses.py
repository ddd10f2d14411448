"""The still-pose search (calibration/poses.py) against its definition.

A window of ``window`` consecutive scans is still when every scan in it is valid and no
channel changes by more than ``band_volts`` peak to peak within it; a scan is still when it
lies in a still window; a stretch is a maximal run of still scans (so it never spans an
invalid scan), split into pieces of at most ``max_scans`` if asked; a pose is the mean and
standard deviation of its stretch's readings. The search is checked against a brute-force
finder written from those sentences, and each pose against ``np.mean`` and ``np.std`` of its
scans, on long hand-moved streams and on small streams hypothesis draws on a grid of
readings (so that a peak-to-peak of exactly the band occurs), not against any former code.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from loopcal.calibration.errors import InputError
from loopcal.calibration.poses import StillPoses, running_sums_at, still_poses
from loopcal.calibration.simulate import quantize_volts
from tests.support.fuzz import examples
from tests.support.plate import held_and_moved

EPS = np.finfo(float).eps


def still_windows(V, window, band_volts, valid):
    """(n - window + 1,) whether the window of scans i .. i + window - 1 is still, by
    looking at each of its scans in turn (offset d of every window at once)."""
    m = len(V) - window + 1
    hi, lo, ok = V[:m].copy(), V[:m].copy(), valid[:m].copy()
    for d in range(1, window):
        hi = np.maximum(hi, V[d : d + m])
        lo = np.minimum(lo, V[d : d + m])
        ok &= valid[d : d + m]
    return ok & np.all(hi - lo <= band_volts, axis=1)


def brute_force_stretches(V, window=10, band_volts=0.25, valid=None):
    """The still stretches [a, b) of V by the definition (module docstring)."""
    n = len(V)
    valid = np.ones(n, dtype=bool) if valid is None else valid
    if n < window:
        return []
    win = still_windows(V, window, band_volts, valid)
    still = np.zeros(n, dtype=bool)
    for d in range(window):  # scan i + d of every still window i
        still[d : d + len(win)] |= win
    stretches, start = [], None
    for j, s in enumerate([*still.tolist(), False]):
        if s and start is None:
            start = j
        elif not s and start is not None:
            stretches.append((start, j))
            start = None
    return stretches


def check_poses(V, sp, *, window=10, band_volts=0.25, max_scans=None, valid=None):
    """Everything the definition says about the result ``sp`` of still_poses(V, ...)."""
    n = len(V)
    ok = np.ones(n, dtype=bool) if valid is None else valid
    k = len(sp)
    assert isinstance(sp, StillPoses)
    assert sp.ranges.shape == (k, 2) and np.issubdtype(sp.ranges.dtype, np.integer)
    assert sp.volts.shape == (k, 4) and sp.spread.shape == (k, 4)
    assert np.array_equal(sp.counts, sp.ranges[:, 1] - sp.ranges[:, 0])
    a, b = sp.ranges.T
    assert np.all(a >= 0) and np.all(b <= n)
    assert np.all(a[1:] >= b[:-1])  # in order, not overlapping
    assert np.all(b - a >= window)
    stretches = brute_force_stretches(V, window, band_volts, ok)
    if max_scans is None:
        assert [tuple(r) for r in sp.ranges.tolist()] == stretches  # none missed, none extra
    else:
        assert np.all(b - a <= max_scans)
        check_pieces(sp.ranges, stretches, window, max_scans)
    # every pose: valid scans only; its mean and (population) standard deviation, here by
    # a sum over its scans and a second pass over their deviations from its mean
    if k == 0:
        return
    rows = np.concatenate([np.arange(x, y) for x, y in sp.ranges.tolist()])
    assert ok[rows].all()
    first = np.cumsum(sp.counts) - sp.counts
    cnt = sp.counts[:, None]
    mean = np.add.reduceat(V[rows], first) / cnt
    var = np.add.reduceat((V[rows] - np.repeat(mean, sp.counts, axis=0)) ** 2, first) / cnt
    # the running sums over the stream up to a pose, differenced, round differently: by
    # about sqrt(b) roundings of sums up to b * scale
    scale = max(1.0, float(np.abs(V).max()))
    b = sp.ranges[:, 1:]
    tol = 4 * EPS * np.sqrt(b + 1) * (b + 1) * scale / cnt
    assert np.all(np.abs(sp.volts - mean) <= tol)
    assert np.all(sp.spread >= 0)
    assert np.all(np.abs(sp.spread**2 - var) <= tol * scale)
    for i in {0, k // 2, k - 1}:  # and a few by numpy's own mean and std
        (x, y), t = sp.ranges[i], tol[i]
        assert np.all(np.abs(sp.volts[i] - np.mean(V[x:y], axis=0)) <= t)
        assert np.all(np.abs(sp.spread[i] ** 2 - np.std(V[x:y], axis=0) ** 2) <= t * scale)


def check_pieces(ranges, stretches, window, max_scans):
    """Each stretch split into pieces of at most max_scans: contiguous from its start, none
    shorter than the window, no more of them than needed, fewer than ``window`` of its
    scans left over; a stretch no longer than max_scans kept whole; no piece elsewhere."""
    pieces = [tuple(r) for r in ranges.tolist()]
    i = 0
    for x, y in stretches:
        mine = []
        while i < len(pieces) and pieces[i][0] < y:
            assert pieces[i][0] >= x  # not before this stretch (nor in a previous one)
            mine.append(pieces[i])
            i += 1
        if y - x <= max_scans:
            assert mine == [(x, y)]
            continue
        assert len(mine) <= -(-(y - x) // max_scans)
        end = x
        for c, d in mine:
            assert c == end and window <= d - c <= max_scans
            end = d
        assert end <= y and y - end < window
    assert i == len(pieces)  # none after the last stretch


def hand_moves(rng, n, noise=0.04):
    """Readings of a plate moved and held still in turn, quantised like the DAQ's."""
    return quantize_volts(held_and_moved(rng, n, hold=(5, 160), move=(3, 40), noise=noise))[1]


def test_the_brute_force_finder_itself():
    """The reference on streams whose stretches are known by construction."""
    V = np.zeros((30, 4))
    V[10:13] = [[1, 0, 0, 0], [2, 0, 0, 0], [3, 0, 0, 0]]  # channel 1 out and back
    assert brute_force_stretches(V, window=5, band_volts=0.5) == [(0, 10), (13, 30)]
    assert brute_force_stretches(V, window=5, band_volts=1.0) == [(0, 11), (13, 30)]
    assert brute_force_stretches(V, window=5, band_volts=2.0) == [(0, 12), (13, 30)]
    assert brute_force_stretches(V, window=5, band_volts=3.0) == [(0, 30)]
    valid = np.ones(30, dtype=bool)
    valid[20] = False
    assert brute_force_stretches(V, 5, 3.0, valid) == [(0, 20), (21, 30)]
    valid[18] = False  # 19 alone cannot make a window
    assert brute_force_stretches(V, 5, 3.0, valid) == [(0, 18), (21, 30)]
    assert brute_force_stretches(V, 10, 3.0, valid) == [(0, 18)]


@pytest.mark.parametrize("seed", range(4))
def test_hand_moved_streams(seed):
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
        assert len(sp) > 50
        check_poses(V, sp, **kw)


@pytest.mark.parametrize("window", [2, 3, 4, 7, 8, 10, 16, 25])
def test_every_window_length_across_long_streams(window):
    """Streams around sizes a blocked search may cut at (powers of two), and windows of
    every kind of length (powers of two, one off them, odd)."""
    rng = np.random.default_rng(100 + window)
    band = 0.2 + 0.01 * window  # noise of 40 mV: some windows still, some not
    for n in (window, window + 1, (1 << 14) + window - 1, (1 << 14) + window, 40_000):
        V = hand_moves(rng, n)
        sp = still_poses(V, window=window, band_volts=band)
        check_poses(V, sp, window=window, band_volts=band)
        assert n < 1000 or len(sp) > 50
        valid = rng.random(n) > 0.01
        sp = still_poses(V, window=window, band_volts=band, valid=valid, max_scans=window + 7)
        check_poses(V, sp, window=window, band_volts=band, valid=valid, max_scans=window + 7)


# readings on a grid of 1/8 V, walking a few steps at a time, so that stretches are common
# and a peak-to-peak of exactly the band is too (sums of multiples of 1/8 are exact)
STEPS = st.sampled_from([0, 0, 0, 0, 0, 0, 1, -1, 2, -3])


@st.composite
def streams(draw):
    n = draw(st.integers(0, 90))
    window = draw(st.integers(2, 9))
    steps = draw(arrays(np.int64, (n, 4), elements=STEPS))
    V = np.cumsum(steps, axis=0) / 8.0 + draw(st.integers(-40, 40)) / 8.0
    band = draw(st.integers(0, 4)) / 8.0
    valid = draw(
        st.one_of(st.none(), arrays(bool, (n,), elements=st.sampled_from([True] * 7 + [False])))
    )
    max_scans = draw(st.one_of(st.none(), st.integers(window, 3 * window)))
    return V, {"window": window, "band_volts": band, "valid": valid, "max_scans": max_scans}


@pytest.mark.slow
@settings(max_examples=examples(400), deadline=None, derandomize=True, database=None)
@given(streams())
def test_small_streams_meet_the_definition(stream):
    V, kw = stream
    check_poses(V, still_poses(V, **kw), **kw)


@pytest.mark.slow
@settings(max_examples=examples(100), deadline=None, derandomize=True, database=None)
@given(streams(), st.floats(-1e3, 1e3))
def test_readings_of_invalid_scans_do_not_matter(stream, junk):
    V, kw = stream
    if kw["valid"] is None:
        return
    sp = still_poses(V, **kw)
    W = V.copy()
    W[~kw["valid"]] = junk
    other = still_poses(W, **kw)
    assert np.array_equal(other.ranges, sp.ranges)
    assert np.allclose(other.volts, sp.volts, rtol=0, atol=1e-9)


def test_the_band_and_the_window_are_inclusive():
    V = np.zeros((12, 4))
    V[::2, 2] = 0.25  # channel 3 alternates: 0.25 V peak to peak everywhere
    assert np.array_equal(still_poses(V, band_volts=0.25).ranges, [[0, 12]])
    assert len(still_poses(V, band_volts=0.2499)) == 0
    V = np.zeros((25, 4))
    V[10] = 2.5
    V[11:] = 5.0  # still for 10 scans, a move, still for 14
    assert np.array_equal(still_poses(V, window=10).ranges, [[0, 10], [11, 25]])
    assert np.array_equal(still_poses(V, window=11).ranges, [[11, 25]])
    assert np.array_equal(still_poses(V, window=14).ranges, [[11, 25]])
    assert len(still_poses(V, window=15)) == 0
    check_poses(V, still_poses(V, window=10, max_scans=12), window=10, max_scans=12)
    p = still_poses(V, window=10)
    assert np.array_equal(p.volts, [[0.0] * 4, [5.0] * 4]) and not p.spread.any()


def test_edge_cases():
    for V in (np.zeros((0, 4)), np.zeros((9, 4))):  # empty, shorter than a window
        sp = still_poses(V)
        assert len(sp) == 0 and sp.ranges.shape == (0, 2) and sp.volts.shape == (0, 4)
        assert sp.spread.shape == (0, 4) and len(sp.counts) == 0
    assert np.array_equal(still_poses(np.zeros((10, 4))).ranges, [[0, 10]])  # all still
    flat = np.full((1000, 4), 1.25)
    sp = still_poses(flat, max_scans=300)
    assert sp.ranges[0, 0] == 0 and sp.ranges[-1, 1] >= 1000 - 9 and len(sp) == 4
    check_poses(flat, sp, max_scans=300)
    moving = np.outer(np.arange(100.0), np.ones(4))
    assert len(still_poses(moving)) == 0
    slow = np.outer(np.arange(100.0) * 0.025, np.ones(4))  # 0.225 V over 10 scans: still
    assert np.array_equal(still_poses(slow).ranges, [[0, 100]])
    assert len(still_poses(np.zeros((100, 4)), valid=np.zeros(100, dtype=bool))) == 0
    every_other = np.arange(100) % 2 == 0
    assert len(still_poses(np.zeros((100, 4)), window=2, valid=every_other)) == 0


def test_bad_input_is_refused():
    V = np.zeros((50, 4))
    for bad in (np.nan, np.inf):
        W = V.copy()
        W[7, 2] = bad
        with pytest.raises(InputError, match="NaN or infinite"):
            still_poses(W)
        with pytest.raises(InputError, match="NaN or infinite"):  # even where not valid
            still_poses(W, valid=np.arange(50) != 7)
    with pytest.raises(InputError, match="at least 2 scans"):
        still_poses(V, window=1)
    with pytest.raises(InputError, match="valid must have shape"):
        still_poses(V, valid=np.ones(49, dtype=bool))
    with pytest.raises(InputError, match="max_scans"):
        still_poses(V, window=10, max_scans=9)
    with pytest.raises(InputError, match="shape"):
        still_poses(np.zeros((50, 3)))


def test_running_sums_are_cumsums_bit_for_bit():
    rng = np.random.default_rng(5)
    for n in (1, 5, 1000, (1 << 14) - 1, 1 << 14, (1 << 14) + 1, 3 * (1 << 14) + 17, 70_001):
        X = rng.normal(3.0, 2.0, (n, 3)) * 10.0 ** rng.integers(-3, 4, (n, 1))
        S = np.concatenate([np.zeros((1, 3)), np.cumsum(X, axis=0)])
        at = np.concatenate([[0, n, n, 0], rng.integers(0, n + 1, 500)])  # any order, repeats
        got = running_sums_at(lambda a, b: X[a:b].copy(), n, at)  # noqa: B023
        assert np.array_equal(got, S[at])
        for last in (0, 1, n // 3, n - 1):
            early = np.append(at[at <= last], last)
            reads = []
            got = running_sums_at(
                lambda a, b: reads.append((a, b)) or X[a:b].copy(),  # noqa: B023
                n,
                early,
            )
            assert np.array_equal(got, S[early])
            # in order, each row once, and no rows past the last index asked for
            spans = [(a, b) for a, b in reads if b > a]
            assert [a for a, _ in spans] == [0, *(b for _, b in spans)][: len(spans)]
            assert all(a < last for a, _ in spans)
            assert last == 0 or spans[-1][1] >= last
    X = np.ones((10, 2))
    assert np.array_equal(running_sums_at(lambda a, b: X[a:b].copy(), 10, [0, 0]), np.zeros((2, 2)))
    assert running_sums_at(lambda a, b: X[a:b].copy(), 0, [0]).shape == (1, 2)
