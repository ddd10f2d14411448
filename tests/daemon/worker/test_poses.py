"""The worker's still poses (daemon/worker/recorded_poses.py) against what its docstrings say, each
part computed here independently from the scan rows' fields:

- a scan is left out if a channel is at the rail (status bits 0-3, or a code of 0 or
  4095) or faulted (status bits 4-7), or if it lies within the gap margin of a break: a row
  with scans missed just before it, a restart, or a change of power-on epoch (the margin's
  scans before the break and from it on);
- the poses are those :func:`loopcal.calibration.poses.still_poses` finds in each clean
  stretch (a maximal run of scans not left out) on its own;
- a pose's scan noise is ``sqrt(mean(diff^2) / 2)`` of its scan-to-scan differences, its
  noise the scan noise averaged down plus the 12-bit rounding, its stamp its middle time.

On recordings of the simulated mechanism with gaps, restarts, a power cycle, rail and fault
scans, and on synthetic recordings hypothesis draws at several scan rates.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopcal.calibration.poses import still_poses
from loopcal.daemon.worker.recorded_poses import poses_of_scans
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.scenarios import HandMoves
from tests.support.fuzz import examples
from tests.support.rows import (
    LSB,
    near_a_break,
    readings,
    rows_from,
    synthetic_scans,
    untrustworthy,
)
from tests.support.sessions import PAUSE_S, truth_for

EPS = np.finfo(float).eps


def check_recorded_poses(s, got, *, rate, window, band_volts, margin, longest):
    """``got`` = poses_of_scans(s) with windows of ``window`` scans, ``margin`` scans
    of gap margin and poses of at most ``longest`` scans at ``rate`` Hz."""
    n = len(s)
    V = readings(s)
    bad = untrustworthy(s)
    near = near_a_break(s, margin)
    usable = ~bad & ~near
    assert got.dropped == {
        "channel at the rail or faulted": int(bad.sum()),
        "next to a gap or restart": int((near & ~bad).sum()),
    }
    same = (np.diff(s["epoch"]) == 0) & (np.diff(s["counter64"].astype(np.int64)) == 1)
    if not same.any():  # no two consecutive scans: the datasheet's default rate, no pose
        assert got.scan_rate_hz == 20.0 and len(got) == 0
        return
    assert got.scan_rate_hz == pytest.approx(rate, rel=1e-12)
    k = len(got)
    assert got.rows.shape == (k, 2) and got.volts.shape == (k, 4)
    assert got.spread.shape == (k, 4) and got.scan_noise.shape == (k, 4)
    assert np.array_equal(got.counts, got.rows[:, 1] - got.rows[:, 0])
    for a, b in got.rows.tolist():
        assert usable[a:b].all()  # no rail, fault, or scan near a gap or restart
    # still_poses on each clean stretch on its own
    ranges, volts, spread = [], [], []
    ok, j = usable.tolist(), 0
    while j < n:
        if not ok[j]:
            j += 1
            continue
        end = j
        while end < n and ok[end]:
            end += 1
        sp = still_poses(V[j:end], window=window, band_volts=band_volts, max_scans=longest)
        ranges.append(sp.ranges + j)
        volts.append(sp.volts)
        spread.append(sp.spread)
        j = end
    ranges = np.concatenate([np.zeros((0, 2), dtype=int), *ranges])
    assert np.array_equal(got.rows, ranges)
    if k == 0:
        return
    b = got.rows[:, 1:]
    cnt = got.counts[:, None]
    # the sums over the recording up to a pose round differently from those over a stretch
    tol = 8 * EPS * np.sqrt(b + 1) * np.cumsum(np.abs(V), axis=0)[b[:, 0] - 1] / cnt
    assert np.all(np.abs(got.volts - np.concatenate(volts)) <= tol)
    scale = 1 + np.abs(V).max()
    assert np.all(np.abs(got.spread**2 - np.concatenate(spread) ** 2) <= 4 * tol * scale)
    # each pose's scan noise and noise, by their formulas
    d2 = np.concatenate([np.zeros((1, 4)), np.diff(V, axis=0) ** 2])
    size = np.cumsum(d2, axis=0)[b[:, 0] - 1]
    # sqrt(mean(diff^2) / 2) over the pose's differences V[j + 1] - V[j], x <= j < y - 1
    pairs = np.concatenate([np.arange(x, y - 1) for x, y in got.rows.tolist()])
    squares = (V[pairs + 1] - V[pairs]) ** 2
    m = got.counts - 1
    noise = np.sqrt(np.add.reduceat(squares, np.cumsum(m) - m) / m[:, None] / 2)
    x, y = got.rows[0]  # one by numpy's own mean too
    assert np.allclose(noise[0], np.sqrt(np.mean(np.diff(V[x:y], axis=0) ** 2, axis=0) / 2))
    assert np.all(np.abs(got.scan_noise**2 - noise**2) <= 8 * EPS * np.sqrt(b + 1) * size / cnt)
    assert np.allclose(
        got.noise_volts, np.sqrt(noise**2 / cnt + LSB**2 / 12), rtol=1e-6, atol=1e-12
    )
    # the middle time
    first, last = s["stamp_ns"][got.rows[:, 0]], s["stamp_ns"][got.rows[:, 1] - 1]
    assert np.all((first <= got.stamp_ns) & (got.stamp_ns <= last))
    off = 2 * got.stamp_ns.astype(np.int64) - first - last  # twice the offset from the middle
    assert np.all(np.abs(off) <= 1_000_000_000 // rate)  # within half a scan of it


# --- recordings of the simulated mechanism --------------------------------------------------


def damaged_scans(seed: int, minutes: float = 20.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    truth = truth_for(seed)
    n = round(minutes * 60 * 20)
    time_us, codes = mechanism_scans(HandMoves(seed, params=truth, pause_s=PAUSE_S), truth, n,
                                     seed=seed)  # fmt: skip
    s = rows_from(time_us, codes)
    s["missed"][rng.integers(0, n, 30)] = 4
    s["restarted"][rng.integers(0, n, 3)] = True
    s["missed"][:3] = 1  # a gap at the very start
    s["missed"][-2] = 2  # and one at the end
    s["epoch"][n // 2 :] += 1  # a power cycle
    s["status"][rng.integers(0, n, 200)] |= 1 << 6  # sensor faults
    s["codes"][rng.integers(0, n, 200), 1] = 4095  # rail
    return s


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_poses_of_a_damaged_recording(seed):
    s = damaged_scans(seed)
    got = poses_of_scans(s)
    assert len(got) > 300
    # the defaults: 0.5 s windows, 0.25 V, 0.25 s of margin, poses of at most 5 s, at 20 Hz
    check_recorded_poses(s, got, rate=20, window=10, band_volts=0.25, margin=5, longest=100)
    assert got.dropped["next to a gap or restart"] > 0
    assert got.dropped["channel at the rail or faulted"] > 0
    wider = poses_of_scans(s, window_s=0.8, band_volts=0.3, gap_margin_s=0.5, longest_s=2.0)
    check_recorded_poses(s, wider, rate=20, window=16, band_volts=0.3, margin=10, longest=40)


# --- synthetic recordings --------------------------------------------------------------------


@st.composite
def recordings(draw):
    n = draw(st.integers(0, 1500))
    rate = draw(st.sampled_from([10, 20, 50]))
    window = draw(st.integers(2, 12))
    longest = draw(st.integers(window, 4 * window))
    margin = draw(st.integers(1, 6))
    counts = {
        key: draw(st.integers(0, max(1, n // 60)))
        for key in ("gaps", "restarts", "power_cycles", "bad")
    }
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    s = synthetic_scans(rng, n, rate, **counts)
    band = draw(st.sampled_from([0.15, 0.25, 0.4]))
    return s, {"rate": rate, "window": window, "band_volts": band, "margin": margin,
               "longest": longest}  # fmt: skip


@settings(max_examples=examples(80), deadline=None, derandomize=True, database=None)
@given(recordings())
def test_synthetic_recordings(recording):
    s, kw = recording
    rate = kw["rate"]
    got = poses_of_scans(
        s,
        window_s=kw["window"] / rate,
        band_volts=kw["band_volts"],
        gap_margin_s=kw["margin"] / rate,
        longest_s=kw["longest"] / rate,
    )
    check_recorded_poses(s, got, **kw)


@pytest.mark.slow
def test_a_long_recording():
    """A few hundred thousand scans (conversions and checks in blocks, if so, cut it)."""
    rng = np.random.default_rng(5)
    s = synthetic_scans(rng, 3 * 65_536 + 123, 20, gaps=80, restarts=5, power_cycles=2,
                        bad=2000)  # fmt: skip
    got = poses_of_scans(s)
    assert len(got) > 1000
    check_recorded_poses(s, got, rate=20, window=10, band_volts=0.25, margin=5, longest=100)


def test_breaks_and_bad_scans_at_the_edges():
    rng = np.random.default_rng(1)
    s = synthetic_scans(rng, 400, 20)
    V = readings(s)
    clean = poses_of_scans(s)
    check_recorded_poses(s, clean, rate=20, window=10, band_volts=0.25, margin=5, longest=100)
    assert clean.dropped == {"channel at the rail or faulted": 0, "next to a gap or restart": 0}
    whole = still_poses(V, max_scans=100)
    assert np.array_equal(clean.rows, whole.ranges)
    s["missed"][0] = 3  # a gap before the first scan, a restart at the last
    s["restarted"][-1] = True
    s["status"][[1, 2, 200]] |= 0x10  # faults, one next to the gap at the start
    s["codes"][201, 3] = 0
    got = poses_of_scans(s)
    check_recorded_poses(s, got, rate=20, window=10, band_volts=0.25, margin=5, longest=100)
    assert got.dropped == {"channel at the rail or faulted": 4, "next to a gap or restart": 9}
    assert got.rows.min(initial=400) >= 5 and got.rows.max(initial=0) <= 394
    everything_bad = s.copy()
    everything_bad["codes"][:, 2] = 4095
    none = poses_of_scans(everything_bad)
    assert len(none) == 0 and none.dropped["channel at the rail or faulted"] == 400
    for n in (0, 1, 5, 9):
        few = poses_of_scans(s[:n])
        assert len(few) == 0 and few.rows.shape == (0, 2) and few.noise_volts.shape == (0, 4)
