"""The worker's still poses (daemon/worker/poses.py) against the version before issue #16
(the scans next to a gap marked by a Python loop over the gaps, the readings converted
twice, running sums in fresh arrays): the same poses, bit for bit, on a recording with
gaps, restarts, a power cycle, rail and fault scans."""

import numpy as np
from session_helpers import PAUSE_S, rows_from, truth_for

from loopcal.calibration.poses import still_poses
from loopcal.daemon import scans as scan_rows
from loopcal.daemon.worker.poses import GAP_MARGIN_S, _near, poses_of_scans
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.scenarios import HandMoves


def reference_noise(volts, ranges):
    if len(ranges) == 0:
        return np.zeros((0, 4))
    d2 = np.concatenate([np.zeros((1, 4)), np.diff(volts, axis=0) ** 2])
    c = np.concatenate([np.zeros((1, 4)), np.cumsum(d2, axis=0)])
    a, b = ranges[:, 0] + 1, ranges[:, 1]
    return np.sqrt((c[b] - c[a]) / np.maximum(b - a, 1)[:, None] / 2)


def reference_poses(s, window_s=0.5, band_volts=0.25, gap_margin_s=GAP_MARGIN_S, longest_s=5.0):
    n = len(s)
    rate = scan_rows.scan_rate_hz(s)
    bad_channel = ~scan_rows.trustworthy(s).all(axis=1)
    breaks = np.flatnonzero((s["missed"] > 0) | s["restarted"])
    if n:
        breaks = np.union1d(breaks, np.flatnonzero(np.diff(s["epoch"]) != 0) + 1)
    margin = max(1, round(gap_margin_s * rate))
    near_gap = np.zeros(n, dtype=bool)
    for b in breaks:
        near_gap[max(0, b - margin) : b + margin] = True
    window = max(2, round(window_s * rate))
    found = still_poses(
        scan_rows.volts(s), window=window, band_volts=band_volts,
        max_scans=max(window, round(longest_s * rate)), valid=~bad_channel & ~near_gap,
    )  # fmt: skip
    dropped = {
        "channel at the rail or faulted": int(bad_channel.sum()),
        "next to a gap or restart": int((near_gap & ~bad_channel).sum()),
    }
    return found, reference_noise(scan_rows.volts(s), found.ranges), dropped


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


def test_near_gap_is_the_loop_it_replaced():
    rng = np.random.default_rng(0)
    for n, margin in ((1000, 5), (50, 5), (7, 3), (0, 5)):
        breaks = np.unique(rng.integers(0, max(n, 1), 12)) if n else np.zeros(0, dtype=int)
        expected = np.zeros(n, dtype=bool)
        for b in breaks:
            expected[max(0, b - margin) : b + margin] = True
        assert np.array_equal(_near(breaks, margin, n), expected)


def test_same_poses_as_before():
    for seed in (1, 2):
        s = damaged_scans(seed)
        got = poses_of_scans(s)
        found, noise, dropped = reference_poses(s)
        assert len(got) > 300
        assert np.array_equal(got.rows, found.ranges)
        assert np.array_equal(got.volts, found.volts)
        assert np.array_equal(got.spread, found.spread)
        assert np.array_equal(got.scan_noise, noise)
        assert got.dropped == dropped
        assert dropped["next to a gap or restart"] > 0
        assert dropped["channel at the rail or faulted"] > 0
    assert len(poses_of_scans(s[:0])) == 0
    assert len(poses_of_scans(s[:5])) == 0
