"""MCAP -> poses: the still stretches of a recording, averaged into calibration poses.

While the plate moves, the four channels of a scan are converted 250 µs apart, so a scan of
a moving plate is skewed; calibration poses therefore come from stretches where the plate is
held still, averaged (:func:`loopcal.calibration.poses.still_poses` finds them). Before that, scans
that must not be in any pose are taken out:

- a channel at the rail or with its sensor-fault bit (the datasheet's untrustworthy reading);
- scans next to a gap or a restart: what the plate did in between is unknown, so a stretch
  never spans one, and the scans within ``gap_margin_s`` of it are not used.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from loopcal.calibration.poses import pose_noise_volts, running_sums_at, still_poses

from .. import scan_rows

STILL_WINDOW_S = 0.5  # a pose spans at least this long
GAP_MARGIN_S = 0.25  # scans this close to a gap or restart are not used
LONGEST_POSE_S = 5.0  # longer stretches are split (a plate may creep while "still")
#: scans kept for the next search of a stream while no pose completes (the plate moving)
POSE_BUFFER_S = 3 * LONGEST_POSE_S


def window_scans(rate: float, window_s: float = STILL_WINDOW_S) -> int:
    """Scans in the still-pose window at ``rate`` Hz (at least 2)."""
    return max(2, round(window_s * rate))


def margin_scans(rate: float, gap_margin_s: float = GAP_MARGIN_S) -> int:
    """Scans left out on each side of a gap or restart at ``rate`` Hz (at least 1)."""
    return max(1, round(gap_margin_s * rate))


@dataclass(frozen=True)
class RecordedPoses:
    """Still poses of a recording.

    volts: (k, 4) mean readings, V. spread: (k, 4) standard deviation of the readings within
    each pose, V. scan_noise: (k, 4) the sensor noise of one reading within each pose, V,
    from scan-to-scan differences (a slow creep of the plate adds to the spread, hardly to
    the differences). counts: (k,) scans averaged. rows: (k, 2) first and one-past-last row of
    the recording's scans. stamp_ns: (k,) the pose's middle time. scan_rate_hz: of the
    recording. dropped: scans left out, by reason.
    """

    volts: np.ndarray
    spread: np.ndarray
    scan_noise: np.ndarray
    counts: np.ndarray
    rows: np.ndarray
    stamp_ns: np.ndarray
    scan_rate_hz: float
    dropped: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.volts)

    @property
    def noise_volts(self) -> np.ndarray:
        """(k, 4) standard deviation of each pose's mean, V
        (:func:`loopcal.calibration.poses.pose_noise_volts`: the scan noise averaged down, the
        12-bit rounding not)."""
        return pose_noise_volts(self.scan_noise, self.counts)


def _difference_noise(volts: np.ndarray, ranges: np.ndarray) -> np.ndarray:
    """(k, 4) noise of one reading within each range [a, b), from first differences:
    sqrt(mean(diff^2) / 2)."""
    if len(ranges) == 0:
        return np.zeros((0, 4))

    def squared_differences(a: int, b: int) -> np.ndarray:  # row j: (V[j] - V[j-1])^2, row 0: 0
        out = np.empty((b - a, 4))
        first = max(a, 1)
        if a == 0:
            out[0] = 0.0
        np.subtract(volts[first:b], volts[first - 1 : b - 1], out=out[first - a :])
        return np.square(out, out=out)

    # differences inside a range: rows a+1 .. b-1
    a, b = ranges[:, 0] + 1, ranges[:, 1]
    c = running_sums_at(squared_differences, len(volts), np.concatenate([b, a]))
    k = len(ranges)
    return np.sqrt((c[:k] - c[k:]) / np.maximum(b - a, 1)[:, None] / 2)


def _near(breaks: np.ndarray, margin: int, n: int) -> np.ndarray:
    """(n,) bool: rows within ``margin`` of a break, [b - margin, b + margin) for each
    break row b (the ranges may overlap)."""
    near = np.zeros(n, dtype=bool)
    rows = (np.asarray(breaks, dtype=np.int64)[:, None] + np.arange(-margin, margin)).ravel()
    near[rows[(rows >= 0) & (rows < n)]] = True
    return near


#: scans converted and checked at a time (no temporaries the size of a day's scans)
_BLOCK = 1 << 16


def _readings(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The readings (n, 4), V, and (n,) whether a channel of the scan is at the rail or
    faulted, a block of scans at a time."""
    n = len(s)
    volts = np.empty((n, 4))
    bad = np.empty(n, dtype=bool)
    for a in range(0, n, _BLOCK):
        part = s[a : a + _BLOCK]
        volts[a : a + _BLOCK] = scan_rows.volts(part)
        bad[a : a + _BLOCK] = ~scan_rows.trustworthy(part).all(axis=1)
    return volts, bad


def completed_poses(
    buf: np.ndarray, *, final: bool = False
) -> tuple[RecordedPoses, list[int], int]:
    """The still poses of a stream's scans so far, as a stream's reader counts them (the
    health monitor, ``loopcal info`` across files): the poses of ``buf`` (SCAN_DTYPE rows,
    in order, not empty), the indices of those the plate has moved on from (every one if
    ``final``: no scan follows), and the row from which ``buf`` is kept for the next search
    (after the last of those, and at most :data:`POSE_BUFFER_S` back)."""
    P = poses_of_scans(buf)
    done = [k for k in range(len(P)) if final or P.rows[k][1] < len(buf)]
    keep_from = int(P.rows[done[-1]][1]) if done else 0
    return P, done, max(keep_from, len(buf) - int(POSE_BUFFER_S * P.scan_rate_hz))


def screen_scans(
    s: np.ndarray, *, gap_margin_s: float = GAP_MARGIN_S
) -> tuple[np.ndarray, np.ndarray, dict[str, int], float]:
    """The readings of scan rows and which of them a calibration may use (module docstring).

    Returns volts (n, 4), V; valid (n,) bool: no channel at the rail or faulted, and not
    within ``gap_margin_s`` of a gap, restart or power cycle; dropped: scans left out, by
    reason; and the recording's scan rate, Hz.
    """
    n = len(s)
    rate = scan_rows.scan_rate_hz(s)
    volts, bad_channel = _readings(s)
    breaks = np.flatnonzero((s["missed"] > 0) | s["restarted"])
    if n:
        epoch_change = np.flatnonzero(np.diff(s["epoch"]) != 0) + 1
        breaks = np.union1d(breaks, epoch_change)
    near_gap = _near(breaks, margin_scans(rate, gap_margin_s), n)
    valid = ~bad_channel & ~near_gap
    dropped = {
        "channel at the rail or faulted": int(bad_channel.sum()),
        "next to a gap or restart": int((near_gap & ~bad_channel).sum()),
    }
    return volts, valid, dropped, rate


def poses_of_scans(
    s: np.ndarray,
    *,
    window_s: float = STILL_WINDOW_S,
    band_volts: float = 0.25,
    gap_margin_s: float = GAP_MARGIN_S,
    longest_s: float = LONGEST_POSE_S,
) -> RecordedPoses:
    """The still poses of scan rows (SCAN_DTYPE, oldest first; see the module docstring).

    window_s: a pose spans at least this long. band_volts: largest peak-to-peak change of a
    channel within such a window that still counts as still (40 mV of noise gives about
    0.2 V over 10 scans). gap_margin_s: scans this close to a gap or restart are left out.
    longest_s: longer still stretches are split into poses of at most this long.
    """
    volts, valid, dropped, rate = screen_scans(s, gap_margin_s=gap_margin_s)
    window = window_scans(rate, window_s)
    found = still_poses(
        volts,
        window=window,
        band_volts=band_volts,
        max_scans=max(window, round(longest_s * rate)),
        valid=valid,
    )
    mid = (found.ranges[:, 0] + found.ranges[:, 1] - 1) // 2
    return RecordedPoses(
        volts=found.volts,
        spread=found.spread,
        scan_noise=_difference_noise(volts, found.ranges),
        counts=found.counts,
        rows=found.ranges,
        stamp_ns=s["stamp_ns"][mid] if len(mid) else np.zeros(0, dtype=np.int64),
        scan_rate_hz=rate,
        dropped=dropped,
    )
