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
    """Standard deviation of each pose's mean reading.

    The noise averages down as 1/sqrt(count); the 12-bit rounding of a still reading does
    not (every scan rounds the same way), so it stays:
    ``sqrt(scan_noise^2 / count + LSB^2 / 12)``.

    Parameters
    ----------
    scan_noise : array_like, shape (k, 4) or (4,)
        The noise of one reading, 1 sigma, V.
    counts : array_like, shape (k,)
        Scans averaged into each pose.

    Returns
    -------
    ndarray, shape (k, 4)
        V.
    """
    counts = np.asarray(counts, dtype=float)
    return np.sqrt(np.square(scan_noise) / counts[:, None] + READING_LSB_VOLTS**2 / 12)


#: scans per block of the sliding-window search and the running sums (their temporaries
#: stay small and are reused: a day's 1.7 M scans are never copied whole)
_BLOCK = 1 << 14


def _sliding(X: np.ndarray, window: int, op) -> np.ndarray:
    """``op`` (np.maximum, np.minimum, np.logical_and or np.logical_or) over every window of
    ``window`` columns of X (c, n): (c, n - window + 1). By doubling: after j steps
    ``m[:, i]`` covers columns i .. i + 2^j - 1, and two overlapping such spans cover any
    window (these operations are exact and idempotent, so the result is that of a reduction
    over each window)."""
    m, span = X, 1
    while 2 * span <= window:
        m = op(m[:, :-span], m[:, span:])
        span *= 2
    return op(m[:, : X.shape[1] - window + 1], m[:, window - span :]) if span < window else m


def _window_spread(V: np.ndarray, window: int, band: float | None = None) -> np.ndarray:
    """(n - window + 1,) the largest peak-to-peak change of any channel within each window
    of ``window`` scans of V (n, c): ``max_c ptp(V[i : i + window, c])``; given ``band``,
    whether that is at most ``band`` instead. In blocks of :data:`_BLOCK` windows, each
    channel-major (O(n log window), no (n, c, window) array)."""
    n = len(V)
    out = np.empty(n - window + 1, dtype=float if band is None else bool)
    o = np.empty(min(_BLOCK, n - window + 1))
    for a in range(0, n - window + 1, _BLOCK):
        X = np.ascontiguousarray(V[a : min(a + _BLOCK + window - 1, n)].T)
        spread = _sliding(X, window, np.maximum)
        spread -= _sliding(X, window, np.minimum)
        m = o[: spread.shape[1]]
        m[:] = spread[0]
        for row in spread[1:]:
            np.maximum(m, row, out=m)
        out[a : a + len(m)] = m if band is None else m <= band
    return out


def _window_all(ok: np.ndarray, window: int) -> np.ndarray:
    """(n - window + 1,) whether every scan of each window of ``window`` scans is ok (n,)."""
    return _sliding(ok[None], window, np.logical_and)[0]


def _covered(starts: np.ndarray, window: int) -> np.ndarray:
    """(n,) for windows of ``window`` scans, whether scan j lies in one of those marked in
    ``starts`` (n - window + 1,): any of starts[j - window + 1 .. j]."""
    pad = np.zeros(window - 1, dtype=bool)
    return _sliding(np.concatenate([pad, starts, pad])[None], window, np.logical_or)[0]


def running_sums_at(rows, n: int, at: np.ndarray) -> np.ndarray:
    """The running sums ``S[j] = X[0] + ... + X[j - 1]`` (S[0] = 0) of n rows X, at given
    indices, without an (n, c) array of X.

    Parameters
    ----------
    rows : callable
        ``rows(a, b)`` returns the rows ``X[a:b]``, shape (b - a, c), as a new array (it is
        summed in place).
    n : int
        Number of rows of X.
    at : array_like of int, shape (m,)
        Indices j into S, ``0 <= j <= n``, in any order.

    Returns
    -------
    ndarray, shape (m, c)
        ``S[at]``.

    Notes
    -----
    The sums are accumulated in order, 16384 rows at a time, each block's first row added
    to the sum before it: bit for bit ``np.cumsum(X, axis=0)`` (which adds in order too);
    blocks past the last index asked are not read.
    """
    at = np.asarray(at, dtype=np.int64)
    order = np.argsort(at, kind="stable")
    where = at[order]
    out = None
    carry = None
    lo = int(np.searchsorted(where, 0, side="right"))  # S[0] = 0
    for a in range(0, n, _BLOCK):
        if lo == len(where):
            break
        b = min(a + _BLOCK, n)
        X = rows(a, b)
        if out is None:
            out = np.zeros((len(at), X.shape[1]))
        if carry is not None:
            X[0] += carry
        np.cumsum(X, axis=0, out=X)
        hi = int(np.searchsorted(where, b, side="right"))
        out[order[lo:hi]] = X[where[lo:hi] - 1 - a]
        carry, lo = X[-1].copy(), hi
    if out is None:  # only S[0] asked for: zeros, as wide as the rows
        out = np.zeros((len(at), rows(0, 0).shape[1]))
    return out


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
    """Still stretches of a scan stream, each averaged into one pose (result of
    :func:`still_poses`).

    Attributes
    ----------
    volts : ndarray, shape (k, 4)
        Mean readings of the still stretches, V.
    spread : ndarray, shape (k, 4)
        Standard deviation of the readings within each stretch, V.
    ranges : ndarray of int, shape (k, 2)
        First and one-past-last scan index of each stretch.
    """

    volts: np.ndarray
    spread: np.ndarray
    ranges: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """Scans averaged into each pose, shape (k,)."""
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

    A scan is still if it lies in at least one window of ``window`` valid scans in which
    every channel stays within ``band_volts`` peak to peak; a stretch is a run of still
    scans.

    Parameters
    ----------
    volts : array_like, shape (n, 4)
        Readings in scan order, V.
    window : int, default 10
        Scans a stretch must at least span (0.5 s at 20 Hz), at least 2.
    band_volts : float, default 0.25
        Largest peak-to-peak change of any channel within a window that still counts as
        still, V (40 mV noise gives about 0.2 V peak-to-peak over 10 scans).
    max_scans : int, optional
        Split longer stretches into pieces of at most this many scans (a last piece shorter
        than ``window`` is dropped); None keeps them whole.
    valid : array_like of bool, shape (n,), optional
        False for scans that must not be used (rail, faults, gaps); a stretch never spans
        an invalid scan.

    Returns
    -------
    StillPoses
        One pose per stretch, in scan order; empty if there are none (or fewer than
        ``window`` scans).

    Raises
    ------
    InputError
        Bad readings, ``window`` below 2, ``valid`` of the wrong shape, or ``max_scans``
        below ``window``.
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
    still_win = _window_spread(V, window, band_volts) & _window_all(ok, window)
    # a scan is still if it lies in at least one still window
    still = _covered(still_win, window)
    edges = np.flatnonzero(np.diff(still, prepend=False, append=False))
    ranges = edges.reshape(-1, 2)
    if max_scans is not None:
        if max_scans < window:
            raise InputError(f"max_scans ({max_scans}) must be at least the window ({window})")
        ranges = _split(ranges, max_scans, window)
    if len(ranges) == 0:
        return empty

    def values_and_squares(a: int, b: int) -> np.ndarray:
        out = np.empty((b - a, 8))
        out[:, :4] = V[a:b]
        np.multiply(V[a:b], V[a:b], out=out[:, 4:])
        return out

    # sums over the stretches from running sums over the scans
    k = len(ranges)
    sums = running_sums_at(values_and_squares, n, ranges.T.ravel())
    total = sums[k:] - sums[:k]
    cnt = (ranges[:, 1] - ranges[:, 0])[:, None]
    mean = total[:, :4] / cnt
    var = np.maximum(total[:, 4:] / cnt - mean**2, 0.0)
    return StillPoses(mean, np.sqrt(var), ranges)
