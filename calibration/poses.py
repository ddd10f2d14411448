"""Quasi-static poses from a stream of scans (docs/model.md section 8).

While the plate moves, the four channels of a scan are converted 250 us apart, and a hand
moves the plate quickly enough for that to matter; so calibration poses come from the still
stretches of a recording, averaged. A stretch is still where, over a window of scans, every
channel stays within a band consistent with its noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .residuals import check_volts

#: one step of the 12-bit converter over its 20 V span, V (DATASHEET: code = floor((V + 10)
#: * 4096 / 20)); rounding to it adds a uniform error of variance LSB^2 / 12 to a reading
READING_LSB_VOLTS = 20.0 / 4096


def pose_noise_volts(scan_noise: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(k, 4) standard deviation of each pose's mean reading, V.

    scan_noise: (k, 4) or (4,) the noise of one reading (V); counts: (k,) scans averaged
    into each pose. The noise averages down as 1/sqrt(count); the 12-bit rounding of a
    still reading does not (every scan rounds the same way), so it stays:
    ``sqrt(scan_noise^2 / count + LSB^2 / 12)``.
    """
    counts = np.asarray(counts, dtype=float)
    return np.sqrt(np.square(scan_noise) / counts[:, None] + READING_LSB_VOLTS**2 / 12)


#: scans per block of the sliding-window search (its temporaries stay in the cache)
_BLOCK = 1 << 14


def _sliding(X: np.ndarray, window: int, op) -> np.ndarray:
    """``op`` (np.maximum or np.minimum) over every window of ``window`` columns of X
    (c, n): (c, n - window + 1). By doubling: after j steps ``m[:, i]`` covers columns
    i .. i + 2^j - 1, and two overlapping such spans cover any window (max and min are
    exact, so the result is that of a reduction over each window)."""
    m, span = X, 1
    while 2 * span <= window:
        m = op(m[:, :-span], m[:, span:])
        span *= 2
    return op(m[:, : X.shape[1] - window + 1], m[:, window - span :]) if span < window else m


def _window_spread(V: np.ndarray, window: int) -> np.ndarray:
    """(n - window + 1,) the largest peak-to-peak change of any channel within each window
    of ``window`` scans of V (n, c): ``max_c ptp(V[i : i + window, c])``. In blocks of
    :data:`_BLOCK` windows, each channel-major (O(n log window), no (n, c, window) array)."""
    n = len(V)
    out = np.empty(n - window + 1)
    for a in range(0, n - window + 1, _BLOCK):
        X = np.ascontiguousarray(V[a : min(a + _BLOCK + window - 1, n)].T)
        spread = _sliding(X, window, np.maximum)
        spread -= _sliding(X, window, np.minimum)
        o = out[a : a + spread.shape[1]]
        o[:] = spread[0]
        for row in spread[1:]:
            np.maximum(o, row, out=o)
    return out


def _window_all(ok: np.ndarray, window: int) -> np.ndarray:
    """(n - window + 1,) whether every scan of each window of ``window`` scans is ok (n,)."""
    bad = np.concatenate([[0], np.cumsum(~ok, dtype=np.int64)])
    return bad[window:] == bad[: len(ok) - window + 1]


def _split(ranges: np.ndarray, max_scans: int, window: int) -> np.ndarray:
    """Ranges (k, 2) [a, b) cut into pieces of max_scans from each start (the last piece
    of a range keeps the rest), pieces shorter than ``window`` dropped; in order."""
    a, b = ranges[:, 0], ranges[:, 1]
    pieces = -(-(b - a) // max_scans)  # ceil
    first = np.repeat(a, pieces)
    step = np.arange(len(first)) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    start = first + step * max_scans
    stop = np.minimum(start + max_scans, np.repeat(b, pieces))
    keep = stop - start >= window
    return np.stack([start[keep], stop[keep]], axis=1).astype(int).reshape(-1, 2)


@dataclass(frozen=True)
class StillPoses:
    """volts: (k, 4) mean readings of the still stretches, V; spread: (k, 4) standard
    deviation of the readings within each stretch, V; ranges: (k, 2) first and one-past-last
    scan index of each stretch; counts: (k,) scans averaged."""

    volts: np.ndarray
    spread: np.ndarray
    ranges: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        return self.ranges[:, 1] - self.ranges[:, 0]

    def __len__(self) -> int:
        return len(self.volts)


def still_poses(
    volts: np.ndarray,
    *,
    window: int = 10,
    band_volts: float = 0.25,
    max_scans: int | None = None,
    valid: np.ndarray | None = None,
) -> StillPoses:
    """Find still stretches in a scan stream and average each into one pose.

    volts: (n, 4) readings in scan order, V. window: scans a stretch must at least span
    (0.5 s at 20 Hz). band_volts: largest peak-to-peak change of any channel within a window
    that still counts as still (40 mV noise gives about 0.2 V peak-to-peak over 10 scans).
    max_scans: split longer stretches into pieces of at most this many scans (None: keep
    whole). valid: (n,) bool, False for scans that must not be used (rail, faults, gaps);
    a stretch never spans an invalid scan.
    """
    V = check_volts(volts)
    n = len(V)
    if window < 2:
        raise InputError(f"a still window needs at least 2 scans, got {window}")
    ok = np.ones(n, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    if ok.shape != (n,):
        raise InputError(f"valid must have shape ({n},), got {ok.shape}")
    empty = StillPoses(np.zeros((0, 4)), np.zeros((0, 4)), np.zeros((0, 2), dtype=int))
    if n < window:
        return empty
    still_win = (_window_spread(V, window) <= band_volts) & _window_all(ok, window)
    # a scan is still if it lies in at least one still window
    cover = np.zeros(n + 1, dtype=np.int64)
    starts = np.flatnonzero(still_win)
    cover[starts] += 1  # starts are distinct, and so are starts + window
    cover[starts + window] -= 1
    still = np.cumsum(cover[:-1]) > 0
    edges = np.flatnonzero(np.diff(still, prepend=False, append=False))
    ranges = edges.reshape(-1, 2)
    if max_scans is not None:
        if max_scans < window:
            raise InputError(f"max_scans ({max_scans}) must be at least the window ({window})")
        ranges = _split(ranges, max_scans, window)
    if len(ranges) == 0:
        return empty
    # sums over the stretches from running sums over the scans (each written in place)
    csum = np.empty((n + 1, 4))
    csum[0] = 0.0
    np.cumsum(V, axis=0, out=csum[1:])
    csq = np.empty((n + 1, 4))
    csq[0] = 0.0
    np.multiply(V, V, out=csq[1:])
    np.cumsum(csq[1:], axis=0, out=csq[1:])
    cnt = (ranges[:, 1] - ranges[:, 0])[:, None]
    mean = (csum[ranges[:, 1]] - csum[ranges[:, 0]]) / cnt
    var = np.maximum((csq[ranges[:, 1]] - csq[ranges[:, 0]]) / cnt - mean**2, 0.0)
    return StillPoses(mean, np.sqrt(var), ranges)
