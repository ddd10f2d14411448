"""Column scaling, observability indices and identifiability analysis (docs/model.md sections 6, 7).

Scaling convention. The identification Jacobian ``g`` (rows: residuals, columns: free
parameters) is scaled as ``g H`` with ``H = diag(sqrt(M) / ||g_j||)``, M the number of poses:
every scaled column has RMS one per pose. This is the paper's unit-column scaling times the
constant ``sqrt(M)``, chosen so that indices compare between pose sets of different size: with
this scaling the standard deviation of a scaled parameter is (residual noise) / s, whatever
M is, so a set of 450 poses with the same spread as a set of 50 has sqrt(9) = 3 times their
singular values, exactly as it has 3 times their precision. With unit columns it would score
the same. The singular values ``s_1 >= ... >= s_L`` of ``g H`` give the indices below.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError, UnobservableError
from .parameters import ParameterModel

# Relative singular value below which a direction counts as not identifiable at all.
UNOBSERVABLE_RTOL = 1e-8
# The paper's acceptable condition number (docs/model.md section 11).
CONDITION_OK = 1000.0


def as_rows(J: np.ndarray) -> tuple[np.ndarray, int]:
    """A Jacobian as 2-D rows and its pose count: (m, 4, n) -> (4 m, n), m."""
    J = np.asarray(J, dtype=float)
    if J.ndim == 3:  # (m, r, n) blocks, one per pose
        return J.reshape(-1, J.shape[-1]), J.shape[0]
    if J.ndim == 2 and J.shape[0] % 4 == 0:
        return J, J.shape[0] // 4
    raise InputError(f"a Jacobian has shape (m, 4, n) or (4m, n), got {J.shape}")


def column_scales(J: np.ndarray, names: tuple[str, ...] | None = None) -> np.ndarray:
    """``diag(H)``: sqrt(M) / ||g_j|| for each column of J ((m, 4, n) or (4m, n)).

    A column of zeros means a parameter with no effect at all on the residuals: it raises
    :class:`UnobservableError` naming it.
    """
    rows, m = as_rows(J)
    norms = np.linalg.norm(rows, axis=0)
    dead = np.flatnonzero(~(norms > 0))
    if dead.size:
        labels = [names[j] if names else f"#{j}" for j in dead]
        raise UnobservableError(
            f"parameters with no effect on the loop residuals: {', '.join(labels)}",
            [{label: 1.0} for label in labels],
        )
    return np.sqrt(m) / norms


@dataclass(frozen=True)
class ObservabilityIndices:
    """The indices of docs/model.md section 7 from the scaled singular values.

    singular_values: (L,) descending. min_singular: s_L (larger is better). condition:
    s_1 / s_L (smaller is better). volume: (s_1 ... s_L)^(1/L) / sqrt(M) with M poses (Borm and
    Menq). noise_amplification: s_L^2 / s_1 (Nahvi and Hollerbach; larger is better).
    a_optimality: trace of the scaled parameter covariance per unit residual variance,
    sum of 1 / s_i^2 (Sun and Hollerbach; smaller is better).
    """

    singular_values: np.ndarray
    n_poses: int

    @property
    def min_singular(self) -> float:
        return float(self.singular_values[-1])

    @property
    def condition(self) -> float:
        s = self.singular_values
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")

    @property
    def volume(self) -> float:
        s = self.singular_values
        with np.errstate(divide="ignore"):
            return float(np.exp(np.mean(np.log(s))) / np.sqrt(self.n_poses))

    @property
    def noise_amplification(self) -> float:
        s = self.singular_values
        return float(s[-1] ** 2 / s[0])

    @property
    def a_optimality(self) -> float:
        s = self.singular_values
        with np.errstate(divide="ignore"):
            return float(np.sum(1.0 / s**2))

    def as_dict(self) -> dict[str, float]:
        return {
            "min_singular": self.min_singular,
            "condition": self.condition,
            "volume": self.volume,
            "noise_amplification": self.noise_amplification,
            "a_optimality": self.a_optimality,
        }


def observability_indices(J: np.ndarray, scales: np.ndarray | None = None) -> ObservabilityIndices:
    """Indices of a pose set from its Jacobian J ((m, 4, n) or (4m, n)).

    scales: ``diag(H)`` to use; default :func:`column_scales` of J itself. Pass a fixed H (for
    example that of a candidate pool) to compare subsets on one scale.
    """
    rows, m = as_rows(J)
    h = column_scales(J) if scales is None else np.asarray(scales, dtype=float)
    s = np.linalg.svd(rows * h, compute_uv=False)
    return ObservabilityIndices(s, m)


@dataclass(frozen=True)
class Combination:
    """A direction in parameter space the data see weakly: ``weights`` over scaled parameters
    (unit norm; the parameter's change times its scale), its singular value and the ratio
    ``s_1 / s``."""

    weights: dict[str, float]
    singular_value: float
    condition: float

    def describe(self, threshold: float = 0.1) -> str:
        terms = sorted(self.weights.items(), key=lambda kv: -abs(kv[1]))
        text = " ".join(f"{w:+.2f}*{n}" for n, w in terms if abs(w) >= threshold)
        return f"{text}  (s = {self.singular_value:.3g}, s1/s = {self.condition:.3g})"


@dataclass(frozen=True)
class IdentifiabilityReport:
    """Which free parameters the pose set can identify (the paper's steps a-c, automated).

    status: name -> "ok" | "weak" | "unobservable": a parameter taking part, with at least
    ``share`` of its squared weight over the singular directions, in a direction below the
    numerical rank is unobservable (its value cannot be told apart from that combination),
    in one beyond the condition limit weak. combinations: those directions,
    weakest first. suggestion: a free set reaching the condition limit by dropping, one at a
    time, the parameter that dominates the weakest direction (followers of a dropped leader
    are dropped with it).
    """

    model: ParameterModel
    indices: ObservabilityIndices
    status: dict[str, str]
    combinations: list[Combination]
    suggestion: ParameterModel | None
    relative_std: dict[str, float]

    @property
    def observable(self) -> bool:
        return all(v != "unobservable" for v in self.status.values())

    def summary(self) -> str:
        ix = self.indices
        lines = [
            f"{self.model.describe()}",
            f"poses {ix.n_poses}: s_min {ix.min_singular:.4g}, condition {ix.condition:.4g}, "
            f"volume {ix.volume:.4g}, noise amplification {ix.noise_amplification:.4g}, "
            f"A-optimality {ix.a_optimality:.4g}",
        ]
        for name, st in self.status.items():
            lines.append(f"  {name:>4}: {st:<12} relative std {self.relative_std[name]:.3g}")
        for c in self.combinations:
            lines.append(f"  weak direction: {c.describe()}")
        if self.suggestion is not None and self.suggestion != self.model:
            lines.append(f"  suggested: {self.suggestion.describe()}")
        return "\n".join(lines)


def _drop(model: ParameterModel, name: str) -> ParameterModel | None:
    free = tuple(n for n in model.free if n != name)
    if not free:
        return None
    return ParameterModel(free, tuple(t for t in model.ties if t.leader != name))


def _condition_of(rows: np.ndarray) -> float:
    s = np.linalg.svd(rows * column_scales(rows), compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def _suggest(rows, model, condition_limit, jacobian_of) -> ParameterModel | None:
    """Drop, one at a time, the parameter whose removal leaves the best-conditioned set,
    until the condition number is within the limit."""
    current, J = model, rows
    while _condition_of(J) > condition_limit:
        best = None
        for j, name in enumerate(current.free):
            reduced = _drop(current, name)
            if reduced is None:
                continue
            Jr = as_rows(jacobian_of(reduced))[0] if jacobian_of else np.delete(J, j, axis=1)
            cond = _condition_of(Jr)
            if best is None or cond < best[0]:
                best = (cond, reduced, Jr)
        if best is None:
            return None
        _, current, J = best
    return current


def analyse_identifiability(
    J: np.ndarray,
    model: ParameterModel,
    *,
    condition_limit: float = CONDITION_OK,
    share: float = 0.05,
    jacobian_of=None,
) -> IdentifiabilityReport:
    """Classify the free parameters of ``model`` from the scaled SVD of J ((m, 4, n)).

    jacobian_of: optional callable ``model -> J`` used to evaluate candidate reduced sets for
    the suggestion; without it the suggestion drops columns of J (the same thing when no ties
    change, which is the usual case).
    """
    rows, m = as_rows(J)
    names = model.free
    if rows.shape[1] != len(names):
        raise InputError(f"Jacobian has {rows.shape[1]} columns for {len(names)} free parameters")
    h = column_scales(rows, names)
    _, s, Vt = np.linalg.svd(rows * h, full_matrices=False)
    ix = ObservabilityIndices(s, m)
    tol = s[0] * UNOBSERVABLE_RTOL
    weak = s < s[0] / condition_limit
    null = s <= tol
    combos = [
        Combination(
            dict(zip(names, Vt[i], strict=True)), float(s[i]), float(s[0] / max(s[i], 1e-300))
        )
        for i in np.flatnonzero(weak)[::-1]
    ]
    status = {}
    with np.errstate(divide="ignore"):
        inv = np.where(null, 0.0, 1.0 / np.maximum(s, tol) ** 2)
    var = (Vt**2 * inv[:, None]).sum(axis=0)
    rel_std = {n: float(np.sqrt(v)) for n, v in zip(names, var, strict=True)}
    for j, name in enumerate(names):
        w = Vt[:, j] ** 2
        if w[null].sum() >= share:
            status[name] = "unobservable"
        elif w[weak].sum() >= share:
            status[name] = "weak"
        else:
            status[name] = "ok"
        if status[name] == "unobservable":
            rel_std[name] = float("inf")
    suggestion = _suggest(rows, model, condition_limit, jacobian_of)
    return IdentifiabilityReport(model, ix, status, combos, suggestion, rel_std)


def require_observable(J: np.ndarray, model: ParameterModel) -> ObservabilityIndices:
    """Raise :class:`UnobservableError` naming the blind combinations if J is rank deficient."""
    rows, m = as_rows(J)
    h = column_scales(J, model.free)
    _, s, Vt = np.linalg.svd(rows * h, full_matrices=False)
    null = s <= s[0] * UNOBSERVABLE_RTOL
    if null.any():
        combos = [dict(zip(model.free, Vt[i], strict=True)) for i in np.flatnonzero(null)]
        text = "; ".join(
            " ".join(f"{w:+.2f}*{n}" for n, w in sorted(c.items(), key=lambda kv: -abs(kv[1]))
                     if abs(w) >= 0.1)
            for c in combos
        )  # fmt: skip
        raise UnobservableError(
            f"the free set cannot be identified from these poses: {null.sum()} parameter "
            f"combination(s) leave every loop residual unchanged ({text}); fix or tie "
            f"parameters (condition number {s[0] / max(s[-1], 1e-300):.3g})",
            combos,
        )
    return ObservabilityIndices(s, m)
