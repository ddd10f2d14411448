"""Which offsets changed: loop closure on every scan, summed over segments of scans.

Each usable scan of a segment (moving or still, the channel skew corrected) is a pose of
its own for :func:`loopcal.calibration.closure.loop_closure`: its whitened error e_k and
the change h_ki of e_k per mm of shift of sensor i's offset. For small shifts
``e_k = h_k . delta + noise``, so a segment is summed up by its normal equations
``N = H^T H``, ``g = H^T e`` (4 x 4 and 4 numbers, scaled by the noise the segment itself
shows), and any set of segments by their sums. The upkeep (:mod:`.upkeep`) keeps three:

- the **baseline**: what the loops showed while nothing changed at the reference. Its
  shift ``b`` and covariance ``C_b`` combine the reference's own calibration (its
  ``[provenance]`` std: the loops of a calibrated config close within it, so a change
  against the calibration is told from the first segment on) with the baseline's segments
  (:func:`baseline_of`); the data take over in what the robot's motion determines;
- a **segment**, tested against the baseline: has anything moved?
- a **change**, the segments since one began: which offsets moved (attribution).

Each test is a generalised likelihood-ratio test with the full covariance of what is
tested, ``g' = g - N b``, ``V = N + N C_b N`` (the segment's noise and the baseline's
uncertainty, which is largest where the motion tells two sensors apart least). An
*explanation* is a set S of offsets that moved by shifts s: ``T_S = z^T F^-1 z`` with
``z = H_S^T V^+ g'``, ``F = H_S^T V^+ H_S`` (``H_S`` the columns S of N), and everything
at once is ``T = g'^T V^+ g'``, chi-square with rank(V) degrees of freedom when nothing
moved. The smallest explanations that leave no significant remainder are compared: one
that beats every other of its size by :data:`MARGIN` (its likelihood 7e7 times theirs)
names the offsets; otherwise every explanation not ruled out is a candidate, and the
change waits for motion that tells them apart.

The loops are linear in the offsets only to first order: a shift of a few mm changes each
scan's pattern h a little, and where two sensors' patterns differ by a few per cent over
the motion seen, that second-order error would decide between them. The upkeep therefore
tests a change's scans linearised at its best explanation (:meth:`Reference.at`: the
reference config moved by that shift), where what is left is small and the test exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations
from typing import Any

import numpy as np
from scipy.special import chdtri

from loopcal.calibration.closure import loop_closure, threshold
from loopcal.calibration.poses import pose_noise_volts
from loopcal.calibration.simulate import NOISE_VOLTS

from ..config.controller import ControllerConfig
from ..worker.offsets import OFFSETS, config_cov
from ..worker.scan_poses import scans_for_fit

#: a segment with fewer usable scans than this is not tested
MIN_SEGMENT_SCANS = 100
#: unchanged segments the baseline takes (then it is held, so that a creep cannot hide in it)
BASELINE_SEGMENTS = 20
#: probability per test of naming a sensor that did not move
FALSE_ALARM = 1e-8
#: the statistic of one sensor's test that says something moved (Bonferroni over four)
LIMIT = threshold(FALSE_ALARM, tests=4)
#: how much likelier the best explanation must be than each other of its size, as a
#: difference of statistics (twice the log-likelihood ratio)
MARGIN = LIMIT
#: eigenvalues of V below this share of the largest carry no information
RANK_TOL = 1e-9


def joint_limit(dof: int) -> float:
    """The chi-square(dof) statistic exceeded with probability :data:`FALSE_ALARM`."""
    return float(chdtri(dof, FALSE_ALARM))


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
    segments : int
        Segments summed.
    """

    N: np.ndarray = field(default_factory=lambda: np.zeros((4, 4)))
    g: np.ndarray = field(default_factory=lambda: np.zeros(4))
    scans: int = 0
    segments: int = 0

    def __add__(self, other: Normal) -> Normal:
        return Normal(
            self.N + other.N,
            self.g + other.g,
            self.scans + other.scans,
            self.segments + other.segments,
        )

    def shifted(self, delta: np.ndarray) -> Normal:
        """The same scans seen at a reference whose offsets are ``delta`` (4,) mm further:
        ``g - N delta`` (the loops are linear in small offset changes)."""
        return Normal(self.N.copy(), self.g - self.N @ delta, self.scans, self.segments)

    def as_json(self) -> dict[str, Any]:
        return {
            "N": self.N.tolist(),
            "g": self.g.tolist(),
            "scans": self.scans,
            "segments": self.segments,
        }

    @classmethod
    def from_json(cls, doc: Any) -> Normal:
        """Raises ValueError (naming what) for anything but :meth:`as_json`'s output."""
        if not isinstance(doc, dict) or set(doc) != {"N", "g", "scans", "segments"}:
            raise ValueError("normal equations: not a table of N, g, scans, segments")
        try:
            N = np.array(doc["N"], dtype=float)
            g = np.array(doc["g"], dtype=float)
        except (TypeError, ValueError):
            raise ValueError("normal equations: N and g must be numbers") from None
        counts = (doc["scans"], doc["segments"])
        if (
            N.shape != (4, 4)
            or g.shape != (4,)
            or not (np.isfinite(N).all() and np.isfinite(g).all())
        ):
            raise ValueError("normal equations: N must be 4 x 4 and g 4 finite numbers")
        if not np.allclose(N, N.T) or np.linalg.eigvalsh(N).min() < -1e-6 * max(1.0, abs(N).max()):
            raise ValueError("normal equations: N is not symmetric positive semi-definite")
        if any(type(c) is not int or c < 0 for c in counts):
            raise ValueError("normal equations: scans and segments must be counts")
        return cls(N, g, *counts)


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
class Reference:
    """What the loops are tested against: the offsets' shift from the reference config
    ``shift`` (4,) mm, and its covariance ``cov`` (4, 4) mm^2."""

    shift: np.ndarray
    cov: np.ndarray

    def moved_by(self, delta: np.ndarray, cov: np.ndarray) -> Reference:
        """This reference after the offsets moved by ``delta`` (4,), known to ``cov``."""
        return Reference(self.shift + delta, self.cov + cov)

    def at(self, point: np.ndarray) -> Reference:
        """The same, for scans linearised at the reference config moved by ``point`` (4,)
        mm: what they show is then the shift beyond ``point``, and an explanation's shift
        is still counted from the reference."""
        return Reference(self.shift - point, self.cov)


def baseline_of(base: Normal, reference: ControllerConfig) -> Reference:
    """The baseline (module docstring): the reference config's own uncertainty (its
    ``[provenance]`` covariance of the offsets, or their std) as a prior, updated by the
    baseline's segments.

    Returns
    -------
    Reference
        ``shift`` = ``C_b g``, ``cov`` = ``C_b`` = ``(C_0^-1 + N)^-1``.
    """
    prior = np.linalg.inv(config_cov(reference))
    cov = np.linalg.inv(prior + base.N)
    cov = (cov + cov.T) / 2
    return Reference(cov @ base.g, cov)


@dataclass(frozen=True)
class Explanation:
    """Some offsets that moved: ``names`` (``"d03"``...), their ``shift_mm`` and
    ``std_mm`` (k,), and the likelihood-ratio ``statistic`` of the explanation."""

    names: tuple[str, ...]
    shift_mm: np.ndarray
    std_mm: np.ndarray
    statistic: float
    cov: np.ndarray  # (k, k) of the shifts, mm^2

    def delta(self) -> tuple[np.ndarray, np.ndarray]:
        """The shift as a (4,) vector of the four offsets and its (4, 4) covariance."""
        idx = [OFFSETS.index(n) for n in self.names]
        d, C = np.zeros(4), np.zeros((4, 4))
        d[idx] = self.shift_mm
        C[np.ix_(idx, idx)] = self.cov
        return d, C

    def words(self) -> str:
        """``d03 +0.60 mm`` (``and`` between offsets)."""
        return " and ".join(
            f"{n} {s:+.2f} mm" for n, s in zip(self.names, self.shift_mm, strict=True)
        )

    def as_json(self) -> dict[str, Any]:
        return {
            "names": list(self.names),
            "shift_mm": [round(float(s), 5) for s in self.shift_mm],
            "std_mm": [round(float(s), 5) for s in self.std_mm],
            "statistic": round(float(self.statistic), 2),
        }


@dataclass(frozen=True)
class OffsetTests:
    """What a test of some scans against a reference found.

    Attributes
    ----------
    shift_mm, std_mm, statistic : ndarray, shape (4,)
        Each sensor's "it alone moved" test: its shift, standard deviation and statistic.
    joint : float
        The statistic of "anything moved", chi-square with ``dof`` degrees of freedom.
    dof : int
        The rank of what the scans tell (4 with motion, fewer with a plate held still).
    moved : bool
        Something moved: a sensor's statistic at :data:`LIMIT`, or the joint one at its
        limit, and the best explanation's largest shift at ``threshold_mm``.
    candidates : list of Explanation
        The explanations not ruled out, best first: the smallest ones that leave no
        significant remainder, within :data:`MARGIN` of the best. One: the change is told;
        more: the motion cannot yet tell them apart.
    """

    shift_mm: np.ndarray
    std_mm: np.ndarray
    statistic: np.ndarray
    joint: float
    dof: int
    moved: bool
    candidates: list[Explanation]

    @property
    def changed(self) -> list[str]:
        """The offsets found moved, when one explanation is told; else empty."""
        return list(self.candidates[0].names) if len(self.candidates) == 1 else []

    @property
    def best(self) -> Explanation | None:
        return self.candidates[0] if self.candidates else None

    def words(self) -> str:
        """The candidates in words: ``d03 +0.58 mm or d04 -0.60 mm``."""
        return " or ".join(c.words() for c in self.candidates)

    def as_dict(self) -> dict[str, dict[str, float]]:
        return {
            n: {
                "shift_mm": round(float(self.shift_mm[i]), 5),
                "std_mm": round(float(self.std_mm[i]), 5),
                "statistic": round(float(self.statistic[i]), 2),
            }
            for i, n in enumerate(OFFSETS)
        }


def offset_tests(data: Normal, against: Reference, *, threshold_mm: float) -> OffsetTests:
    """Test ``data`` (a segment, or a change's segments) against ``against`` (the
    baseline, or the baseline moved by a change).

    Parameters
    ----------
    data : Normal
        The scans tested.
    against : Reference
        What they are expected to show, and how well it is known.
    threshold_mm : float
        The smallest shift that counts, mm.

    Returns
    -------
    OffsetTests
    """
    N = data.N
    gp = data.g - N @ against.shift
    V = N + N @ against.cov @ N
    w, U = np.linalg.eigh((V + V.T) / 2)
    keep = w > RANK_TOL * max(float(w.max()), 1e-300)
    dof = int(keep.sum())
    Vi = (U[:, keep] / w[keep]) @ U[:, keep].T
    joint = float(gp @ Vi @ gp)
    z_all, F_all = N @ Vi @ gp, N @ Vi @ N  # N is symmetric: H = N's columns

    def of_size(k: int) -> list[Explanation]:
        out = []
        for idx in combinations(range(4), k):
            ix = list(idx)
            F, z = F_all[np.ix_(ix, ix)], z_all[ix]
            if np.diag(F).min() <= 0 or np.linalg.cond(F) > 1e12:
                continue
            cov = np.linalg.inv(F)
            s = cov @ z
            names = tuple(OFFSETS[i] for i in ix)
            out.append(Explanation(names, s, np.sqrt(np.diag(cov)), float(z @ s), cov))
        return sorted(out, key=lambda e: -e.statistic)

    singles = {e.names[0]: e for e in of_size(1)}
    shift = np.array([singles[n].shift_mm[0] if n in singles else np.nan for n in OFFSETS])
    std = np.array([singles[n].std_mm[0] if n in singles else np.nan for n in OFFSETS])
    T = np.array([singles[n].statistic if n in singles else 0.0 for n in OFFSETS])
    candidates: list[Explanation] = []
    for k in range(1, 5):  # the smallest size that leaves no significant remainder
        ranked = sorted(singles.values(), key=lambda e: -e.statistic) if k == 1 else of_size(k)
        if not ranked:
            continue
        if dof > k and joint - ranked[0].statistic >= joint_limit(dof - k):
            continue
        top = ranked[0].statistic
        candidates = [e for e in ranked if top - e.statistic < MARGIN]
        break
    significant = float(T.max()) >= LIMIT or (dof > 0 and joint >= joint_limit(dof))
    large = bool(candidates) and float(np.max(np.abs(candidates[0].shift_mm))) >= threshold_mm
    return OffsetTests(shift, std, T, joint, dof, significant and large, candidates)


def segments_normal(rows: np.ndarray, reference: ControllerConfig, edges: np.ndarray) -> Normal:
    """The normal equations of the segments ``[edges[k], edges[k + 1])`` of ``rows`` (by
    their stamps, ns) at ``reference``, summed: a change's scans linearised anew."""
    stamps, out = rows["stamp_ns"], Normal()
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        i, j = np.searchsorted(stamps, [a, b])
        n = segment_normal(rows[i:j], reference) if j > i else None
        if n is not None:
            out = out + n
    return out


def trend(
    end_ns: np.ndarray, shift_mm: np.ndarray, std_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The straight line through segments' shifts, weighted by their variances.

    Parameters
    ----------
    end_ns : ndarray, shape (k,)
        Each segment's end, ns.
    shift_mm, std_mm : ndarray, shape (k,) or (k, m)
        Each segment's shift of one offset (or of m, in columns) and its standard
        deviation, mm.

    Returns
    -------
    slope : ndarray, shape () or (m,)
        mm/s.
    now : ndarray
        The line at the last segment, mm.
    statistic : ndarray
        ``slope^2 / Var(slope)``, chi-square(1) when the shift does not grow.
    """
    s = np.asarray(shift_mm, dtype=float)
    w = 1.0 / np.asarray(std_mm, dtype=float) ** 2
    t = (np.asarray(end_ns, dtype=float) - float(end_ns[0])) / 1e9
    if s.ndim == 2:
        t = t[:, None]
    tm = np.sum(w * t, axis=0) / np.sum(w, axis=0)
    sm = np.sum(w * s, axis=0) / np.sum(w, axis=0)
    spread = np.sum(w * (t - tm) ** 2, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = np.where(spread > 0, np.sum(w * (t - tm) * s, axis=0) / spread, 0.0)
    now = sm + slope * (t[-1] - tm)
    return slope, now, slope * slope * spread


def steplike(end_ns: np.ndarray, shift_mm: np.ndarray, std_mm: np.ndarray) -> bool:
    """Whether segments' shifts of one offset are told better by a step (flat, then flat
    again from some segment on) than by a straight line: a swap, not a creep.

    Parameters
    ----------
    end_ns, shift_mm, std_mm : ndarray, shape (k,)
        As for :func:`trend`.
    """
    s = np.asarray(shift_mm, dtype=float)
    w = 1.0 / np.asarray(std_mm, dtype=float) ** 2
    slope, now, _ = trend(end_ns, s, std_mm)
    t = (np.asarray(end_ns, dtype=float) - float(end_ns[-1])) / 1e9
    line = float(np.sum(w * (s - (now + slope * t)) ** 2))
    best = np.inf
    for k in range(1, len(s)):  # the step at segment k
        a, b = s[:k], s[k:]
        ma, mb = np.average(a, weights=w[:k]), np.average(b, weights=w[k:])
        best = min(best, float(np.sum(w[:k] * (a - ma) ** 2) + np.sum(w[k:] * (b - mb) ** 2)))
    return best < line


def creeps(end_ns: np.ndarray, shift_mm: np.ndarray, std_mm: np.ndarray) -> bool:
    """Whether segments' shifts of one offset grow steadily: their weighted slope in time
    reaches :data:`LIMIT` (:func:`trend`; a creep, where a step's segments before it are
    flat).

    Parameters
    ----------
    end_ns, shift_mm, std_mm : ndarray, shape (k,)
        Each segment's end (ns), the offset's shift in it and its standard deviation, mm.
    """
    return bool(trend(end_ns, shift_mm, std_mm)[2] >= LIMIT)
