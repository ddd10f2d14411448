"""Which offsets changed: loop closure on every scan, summed over segments of scans.

Each usable scan of a segment (moving or still, the channel skew corrected) is a pose of
its own for :func:`loopcal.calibration.closure.loop_closure`: its whitened error e_k and
the change h_ki of e_k per mm of shift of sensor i's offset. For small shifts
``e_k = h_k . delta + noise``, so a segment is summed up by its normal equations
``N = H^T H``, ``g = H^T e`` (4 x 4 and 4 numbers, scaled by the noise the segment itself
shows), and any set of segments by their sums. The upkeep (:mod:`.upkeep`) keeps three:

- the **baseline**: the first unchanged segments after a (re)start, what the loops showed
  before anything changed (its least-squares shift, and that shift's covariance
  ``N^+``); until it has :data:`BASELINE_SEGMENTS`, the reference config's own
  uncertainty stands in. Held fixed afterwards, so that a creep cannot hide in it;
- a **segment**, tested against the baseline: has anything moved?
- a **change**, the segments since one began: which offsets moved (attribution).

The test of "sensor i alone moved by s" against the baseline is the likelihood-ratio
test of the health monitor: ``g'_i = g_i - (N delta_b)_i``, ``s = g'_i / N_ii``,
``T_i = g'_i^2 / Var(g'_i)`` with ``Var = N_ii + (N C_b N)_ii`` (the baseline's own
uncertainty counted), chi-square with one degree of freedom when nothing moved. Two
sensors at once: with the best one's shift taken out, the others once more, jointly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from loopcal.calibration.closure import loop_closure, threshold
from loopcal.calibration.poses import pose_noise_volts
from loopcal.calibration.simulate import NOISE_VOLTS

from ..config.controller import ControllerConfig
from ..worker.offsets import OFFSETS, config_std
from ..worker.scan_poses import scans_for_fit

#: a segment with fewer usable scans than this is not tested
MIN_SEGMENT_SCANS = 100
#: unchanged segments the baseline takes (then it is held): 5 minutes of 15-s segments
BASELINE_SEGMENTS = 20
#: the fewest it needs to stand in for the reference's uncertainty
BASELINE_MIN_SEGMENTS = 4
#: probability per test of naming a sensor that did not move
FALSE_ALARM = 1e-8
LIMIT = threshold(FALSE_ALARM, tests=4)


@dataclass
class Normal:
    """Summed normal equations of loop closure in the four offsets.

    Attributes
    ----------
    N : ndarray, shape (4, 4)
        ``H^T H / scale``, 1/mm^2.
    g : ndarray, shape (4,)
        ``H^T e / scale``, 1/mm.
    scans : int
        Usable scans summed.
    """

    N: np.ndarray = field(default_factory=lambda: np.zeros((4, 4)))
    g: np.ndarray = field(default_factory=lambda: np.zeros(4))
    scans: int = 0
    segments: int = 0

    def __add__(self, other: Normal) -> Normal:
        return Normal(self.N + other.N, self.g + other.g, self.scans + other.scans,
                      self.segments + other.segments)  # fmt: skip


def segment_normal(rows: np.ndarray, reference: ControllerConfig) -> Normal | None:
    """A segment's normal equations at the reference (module docstring).

    Parameters
    ----------
    rows : ndarray of SCAN_DTYPE rows
        The segment's scans, oldest first.
    reference : ControllerConfig
        The parameters the loops are closed at.

    Returns
    -------
    Normal or None
        None when fewer than :data:`MIN_SEGMENT_SCANS` scans are usable.
    """
    usable = scans_for_fit(rows)
    if len(usable) < MIN_SEGMENT_SCANS:
        return None
    volts = usable.volts
    sigma = pose_noise_volts(np.full(4, NOISE_VOLTS), np.ones(len(volts)))
    c = loop_closure(volts, np.asarray(reference.params, dtype=float), sigma)
    H, e = c.offset_pattern[c.usable], c.error[c.usable]
    if len(e) < MIN_SEGMENT_SCANS:
        return None
    N, g = H.T @ H, H.T @ e
    # the noise the segment shows, the best joint shift taken out: an unknown noise level
    # neither hides nor invents a change
    explained = float(g @ np.linalg.lstsq(N, g, rcond=1e-9)[0])
    scale = max(1.0, (float(e @ e) - explained) / max(1, len(e) - 4))
    return Normal(N / scale, g / scale, len(e), 1)


@dataclass(frozen=True)
class OffsetTests:
    """Each sensor's "it alone moved" test against the baseline.

    Attributes
    ----------
    shift_mm, std_mm, statistic : ndarray, shape (4,)
        The shift from the baseline, its standard deviation, and T_i.
    changed : list of str
        The offsets found moved (``"d03"``...): when something moved, the sensor the data
        point at (its likelihood, the baseline's uncertainty left out, above the
        runner-up's by the limit) with its shift at ``threshold_mm``; then a second one
        likewise with the first's shift taken out.
    moved : bool
        Something moved (the best T at the limit and its shift at ``threshold_mm``),
        whichever sensor it was.
    """

    shift_mm: np.ndarray
    std_mm: np.ndarray
    statistic: np.ndarray
    changed: list[str]
    moved: bool

    def as_dict(self) -> dict[str, dict[str, float]]:
        return {n: {"shift_mm": round(float(self.shift_mm[i]), 5),
                    "std_mm": round(float(self.std_mm[i]), 5),
                    "statistic": round(float(self.statistic[i]), 2)}
                for i, n in enumerate(OFFSETS)}  # fmt: skip


def baseline_of(base: Normal, reference: ControllerConfig) -> tuple[np.ndarray, np.ndarray]:
    """(4,) shift of the baseline from the reference, mm, and its (4, 4) covariance: the
    least-squares shift of its segments, or, with fewer than
    :data:`BASELINE_MIN_SEGMENTS`, none and the reference's own uncertainty."""
    if base.segments < BASELINE_MIN_SEGMENTS:
        std = config_std(reference)
        return np.zeros(4), np.diag([std[n] ** 2 for n in OFFSETS])
    cov = np.linalg.pinv(base.N, rcond=1e-9)
    return cov @ base.g, cov


def offset_tests(
    data: Normal, base: Normal, reference: ControllerConfig, *, threshold_mm: float
) -> OffsetTests:
    """Test ``data`` (a segment, or a change's segments) against the baseline ``base``.

    Parameters
    ----------
    data, base : Normal
        The scans tested, and the baseline's.
    reference : ControllerConfig
        The reference both were closed at (its uncertainty stands in for a short baseline).
    threshold_mm : float
        The smallest shift that counts, mm.

    Returns
    -------
    OffsetTests
    """
    shift_b, cov_b = baseline_of(base, reference)
    N = data.N
    g = data.g - N @ shift_b
    var = np.diag(N) + np.einsum("ij,jk,ki->i", N, cov_b, N)
    d = np.diag(N)
    ok = d > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = np.where(ok, g / d, np.nan)
        std = np.where(ok, np.sqrt(var) / d, np.nan)
        T = np.where(ok, g * g / var, 0.0)
    best = int(np.argmax(T))
    moved = bool(T[best] >= LIMIT and abs(shift[best]) >= threshold_mm)
    changed: list[str] = []
    # which sensor: the data's own likelihood of each (the baseline's uncertainty, common
    # to every hypothesis, would blur them all alike)
    with np.errstate(divide="ignore", invalid="ignore"):
        own = np.where(ok, g * g / d, 0.0)
    best = int(np.argmax(own))
    margin = float(own[best] - np.max(np.delete(own, best)))
    if moved and margin >= LIMIT and abs(shift[best]) >= threshold_mm:
        changed.append(OFFSETS[best])
        second = _second(N, g, var, best, threshold_mm)
        if second is not None:
            changed.append(OFFSETS[second])
    return OffsetTests(shift, std, T, sorted(changed), moved)


def _second(N: np.ndarray, g: np.ndarray, var: np.ndarray, first: int,
            threshold_mm: float) -> int | None:  # fmt: skip
    """A second sensor that moved too: each other one fitted jointly with ``first``; it
    counts when its part of the joint fit reaches the limit, its margin over the others as
    large, and its shift ``threshold_mm``."""
    gain = np.zeros(4)
    shifts = np.zeros(4)
    for j in range(4):
        if j == first:
            continue
        idx = [first, j]
        Nj = N[np.ix_(idx, idx)]
        if abs(np.linalg.det(Nj)) < 1e-12 * float(np.prod(np.diag(Nj))):
            continue
        s = np.linalg.solve(Nj, g[idx])
        # the gain over the first alone, on the scale of the tests' variance
        alone = g[first] ** 2 / N[first, first]
        gain[j] = (float(g[idx] @ s) - alone) * N[first, first] / var[first]
        shifts[j] = s[1]
    j = int(np.argmax(gain))
    rest = np.delete(gain, [first, j])
    if gain[j] >= LIMIT and gain[j] - np.max(rest) >= LIMIT and abs(shifts[j]) >= threshold_mm:
        return j
    return None

