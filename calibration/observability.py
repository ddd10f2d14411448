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

from .defaults import CONDITION_OK
from .errors import InputError, UnobservableError
from .parameters import ParameterModel

#: relative singular value (s / s_1) at or below which a direction counts as not
#: identifiable at all
UNOBSERVABLE_RTOL = 1e-8


def as_rows(J: np.ndarray) -> tuple[np.ndarray, int]:
    """A Jacobian as 2-D rows and its pose count.

    Parameters
    ----------
    J : array_like, shape (m, r, n) or (4 m, n)
        Per-pose blocks (r rows each: 4 loop residuals, or 1 information row), or the
        paper's stacked residual rows, pose-major.

    Returns
    -------
    rows : ndarray, shape (m r, n)
    m : int
        Number of poses.

    Raises
    ------
    InputError
        For any other shape.
    """
    J = np.asarray(J, dtype=float)
    if J.ndim == 3:  # (m, r, n) blocks, one per pose
        return J.reshape(-1, J.shape[-1]), J.shape[0]
    if J.ndim == 2 and J.shape[0] % 4 == 0:
        return J, J.shape[0] // 4
    raise InputError(f"a Jacobian has shape (m, 4, n) or (4m, n), got {J.shape}")


def column_scales(J: np.ndarray, names: tuple[str, ...] | None = None) -> np.ndarray:
    """``diag(H)``: ``sqrt(M) / ||g_j||`` for each column of J.

    Parameters
    ----------
    J : array_like, shape (m, r, n) or (4 m, n)
        The identification Jacobian (see :func:`as_rows`), M = m poses.
    names : tuple of str, optional
        The columns' parameter names, for the error message; default ``#0``, ``#1``, ...

    Returns
    -------
    ndarray, shape (n,)
        The scale of each column, in the parameter's unit per unit of the residual.

    Raises
    ------
    UnobservableError
        If a column is zero (or NaN): a parameter with no effect at all on the
        residuals; the error names it.
    InputError
        If J has neither shape.

    Notes
    -----
    The scaled Jacobian ``g H`` has every column of RMS one per pose; see the module
    docstring for why ``sqrt(M)`` rather than unit columns.
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

    Attributes
    ----------
    singular_values : ndarray, shape (L,)
        Singular values of the scaled Jacobian ``g H``, descending.
    n_poses : int
        M, the number of poses.
    """

    singular_values: np.ndarray
    n_poses: int

    @property
    def min_singular(self) -> float:
        """s_L, the smallest singular value (larger is better)."""
        return float(self.singular_values[-1])

    @property
    def condition(self) -> float:
        """s_1 / s_L, the condition number (smaller is better; inf if s_L is 0)."""
        s = self.singular_values
        return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")

    @property
    def volume(self) -> float:
        """(s_1 ... s_L)^(1/L) / sqrt(M) (Borm and Menq; larger is better)."""
        s = self.singular_values
        with np.errstate(divide="ignore"):
            return float(np.exp(np.mean(np.log(s))) / np.sqrt(self.n_poses))

    @property
    def noise_amplification(self) -> float:
        """s_L^2 / s_1 (Nahvi and Hollerbach; larger is better)."""
        s = self.singular_values
        return float(s[-1] ** 2 / s[0])

    @property
    def a_optimality(self) -> float:
        """Sum of 1 / s_i^2 (Sun and Hollerbach; smaller is better): the trace of the scaled
        parameter covariance per unit residual variance."""
        s = self.singular_values
        with np.errstate(divide="ignore"):
            return float(np.sum(1.0 / s**2))

    def as_dict(self) -> dict[str, float]:
        """The five indices by name.

        Returns
        -------
        dict of str to float
            ``min_singular``, ``condition``, ``volume``, ``noise_amplification``,
            ``a_optimality``.
        """
        return {
            "min_singular": self.min_singular,
            "condition": self.condition,
            "volume": self.volume,
            "noise_amplification": self.noise_amplification,
            "a_optimality": self.a_optimality,
        }


def observability_indices(J: np.ndarray, scales: np.ndarray | None = None) -> ObservabilityIndices:
    """Indices of a pose set from its Jacobian.

    Parameters
    ----------
    J : array_like, shape (m, r, n) or (4 m, n)
        The identification Jacobian of m poses (see :func:`as_rows`).
    scales : array_like, shape (n,), optional
        ``diag(H)`` to use; default :func:`column_scales` of J itself. Pass a fixed H (for
        example that of a candidate pool) to compare subsets on one scale.

    Returns
    -------
    ObservabilityIndices
        From the singular values of ``J H``.

    Raises
    ------
    InputError
        If J has neither shape.
    UnobservableError
        If ``scales`` is not given and a column of J is zero.
    """
    rows, m = as_rows(J)
    h = column_scales(J) if scales is None else np.asarray(scales, dtype=float)
    s = np.linalg.svd(rows * h, compute_uv=False)
    return ObservabilityIndices(s, m)


@dataclass(frozen=True)
class Combination:
    """A direction in parameter space the data see weakly.

    Attributes
    ----------
    weights : dict of str to float
        The direction over the scaled parameters (unit norm; a parameter's change divided
        by its column scale), by name.
    singular_value : float
        Its singular value s.
    condition : float
        ``s_1 / s``.
    """

    weights: dict[str, float]
    singular_value: float
    condition: float

    def describe(self, threshold: float = 0.1) -> str:
        """The direction in words, e.g. ``"+0.71*d01 -0.70*A1x  (s = 0.01, s1/s = 2e+03)"``.

        Parameters
        ----------
        threshold : float, default 0.1
            Weights smaller than this in magnitude are left out.

        Returns
        -------
        str
        """
        terms = sorted(self.weights.items(), key=lambda kv: -abs(kv[1]))
        text = " ".join(f"{w:+.2f}*{n}" for n, w in terms if abs(w) >= threshold)
        return f"{text}  (s = {self.singular_value:.3g}, s1/s = {self.condition:.3g})"


@dataclass(frozen=True)
class IdentifiabilityReport:
    """Which free parameters the pose set can identify (the paper's steps a-c, automated).

    Result of :func:`analyse_identifiability`.

    Attributes
    ----------
    model : ParameterModel
        The free set analysed.
    indices : ObservabilityIndices
        Of the scaled Jacobian.
    status : dict of str to str
        Free name -> ``"ok"``, ``"weak"`` or ``"unobservable"``: a parameter taking part,
        with at least ``share`` of its squared weight over the singular directions, in a
        direction below the numerical rank is unobservable (its value cannot be told apart
        from that combination), in one beyond the condition limit weak.
    combinations : list of Combination
        The directions beyond the condition limit, weakest first.
    suggestion : ParameterModel or None
        A free set within the condition limit, found by dropping one parameter at a time,
        each time the one whose removal leaves the best-conditioned set (followers of a
        dropped leader are dropped with it): the model itself if it is within the limit
        already, None if no such set was found.
    relative_std : dict of str to float
        Free name -> standard deviation of the scaled parameter per unit residual noise
        (inf where unobservable).
    """

    model: ParameterModel
    indices: ObservabilityIndices
    status: dict[str, str]
    combinations: list[Combination]
    suggestion: ParameterModel | None
    relative_std: dict[str, float]

    @property
    def observable(self) -> bool:
        """True if no free parameter is unobservable (weak ones are allowed)."""
        return all(v != "unobservable" for v in self.status.values())

    def summary(self) -> str:
        """A readable report: the indices, each parameter's status, the weak directions and
        the suggestion.

        Returns
        -------
        str
        """
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
    """Classify the free parameters of ``model`` from the scaled SVD of J.

    Parameters
    ----------
    J : array_like, shape (m, r, n) or (4 m, n)
        The identification Jacobian of m poses with respect to the free values.
    model : ParameterModel
        The free set, n = ``model.n_free`` columns.
    condition_limit : float, default CONDITION_OK
        Directions with ``s < s_1 / condition_limit`` are weak (1000).
    share : float, default 0.05
        A parameter with at least this share of its squared weight in weak (or
        unobservable) directions is weak (or unobservable).
    jacobian_of : callable, optional
        ``model -> J``, used to evaluate candidate reduced sets for the suggestion; without
        it the suggestion drops columns of J (the same thing when no ties change, which is
        the usual case).

    Returns
    -------
    IdentifiabilityReport

    Raises
    ------
    InputError
        If J's columns do not match the free parameters, or J has neither shape.
    UnobservableError
        If a column of J is zero (a parameter with no effect at all).
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
    """Raise :class:`UnobservableError` naming the blind combinations if J is rank deficient.

    Parameters
    ----------
    J : array_like, shape (m, r, n) or (4 m, n)
        The identification Jacobian with respect to the free values.
    model : ParameterModel
        Names the columns.

    Returns
    -------
    ObservabilityIndices
        Of the scaled Jacobian, when it has full rank.

    Raises
    ------
    UnobservableError
        If a scaled singular value is at most :data:`UNOBSERVABLE_RTOL` times the largest
        (or a column is zero); ``combinations`` holds the blind directions.
    """
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
