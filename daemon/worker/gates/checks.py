"""The acceptance gates as a list: each entry measures its own figure from what the worker
has, says whether it applies to this kind of fit, and judges it.

:data:`GATES` is the list, in the order the worker reports them; :func:`measure_gates` runs
the ones that apply to a :class:`GateContext`. A new gate is one new :class:`Check` in
:data:`GATES` (its judgement beside its kind: :mod:`~loopcal.daemon.worker.gates.samples`,
:mod:`~loopcal.daemon.worker.gates.fit`, :mod:`~loopcal.daemon.worker.gates.residual`)
and one row in docs/calibration.md's table of gates, which a test holds to
:meth:`Check.documented`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from typing import ClassVar

import numpy as np

from loopcal.calibration.identify import Identification
from loopcal.calibration.implicit import score_test
from loopcal.calibration.observability import CONDITION_OK
from loopcal.calibration.parameters import GROUPS, INDEX, NAMES, ParameterModel
from loopcal.calibration.scans import averaging_ratio, closure_misfit

from ..coverage import POSITION_CELL_V, distinct_positions
from ..recorded_poses import RecordedPoses
from . import fit as parameters
from . import residual as closure
from . import samples as motion
from .gate import Advice, Gate, advice_text


@dataclass(frozen=True)
class GateContext:
    """What the gates measure: the samples, and once identified, the fit.

    Parameters
    ----------
    samples : RecordedPoses
        The still poses, or for a fit on every scan the usable scans
        (:class:`~loopcal.daemon.worker.scan_poses.RecordedScans`).
    per_scan : bool
        The fit is on every scan (else on still poses).
    model : ParameterModel
        The free parameters and their ties.
    start : ndarray of float, shape (20,)
        The controller config's parameters, mm and mm/V.
    advice : Advice
        Where to move the plate, for a gate that fails for too little or badly spread
        motion (:class:`~loopcal.daemon.worker.coverage.LazyAdvice`).
    positions : bool, default True
        The ``poses`` gate applies (False: an offset refitted with everything else held
        needs no spread of positions, the daemon's upkeep).
    precision_mm : float, optional
        The ``precision`` gate's limit on lengths, mm (None: its own).
    fit : Identification, optional
        The identification the gates judge; None before it (or when it raised).
    checked : Identification, optional
        The identification the held-out samples check (a fit that did not see them; for
        still poses, ``fit`` itself).
    chosen : ndarray of int, optional
        Indices into ``samples`` of those ``fit`` was given, in its order.
    held_out : ndarray of int, optional
        Indices into ``samples`` of those kept out of ``checked``.
    error : Exception, optional
        Why the identification raised, if it did.
    """

    samples: RecordedPoses
    per_scan: bool
    model: ParameterModel
    start: np.ndarray
    advice: Advice
    positions: bool = True
    precision_mm: float | None = None
    fit: Identification | None = None
    checked: Identification | None = None
    chosen: np.ndarray | None = None
    held_out: np.ndarray | None = None
    error: Exception | None = None

    @cached_property
    def expected_noise(self) -> float:
        """The noise the fitted samples' own scatter predicts, on the fit's footing, V
        (:func:`~loopcal.daemon.worker.gates.residual.expected_noise`; NaN before the fit):
        the paper's fit reports the noise of a pose's mean reading, maximum likelihood that
        of one scan."""
        if self.fit is None:
            return float("nan")
        s = self.samples
        return closure.expected_noise(s.scan_noise[self.chosen], s.counts[self.chosen],
                                      per_scan=self.fit.method == "ml")  # fmt: skip

    @cached_property
    def holdout_z(self) -> np.ndarray:
        """The held-out samples' loop-closure errors at ``checked``, each over its predicted
        standard deviation (:func:`~loopcal.daemon.worker.gates.residual.holdout_residuals`),
        dimensionless."""
        assert self.checked is not None and self.held_out is not None
        s, h = self.samples, self.held_out
        return closure.holdout_residuals(
            s.volts[h], self.checked.params, s.noise_volts[h], model=self.model,
            covariance=self.checked.covariance,
        )  # fmt: skip

    def too_little_motion(self, why: str) -> str:
        """The advice of a gate whose failure follows from too little motion
        (:func:`~loopcal.daemon.worker.gates.samples.too_little_motion` of these samples).

        Parameters
        ----------
        why : str
            What shows it, e.g. ``"condition, min_singular failed"``.

        Returns
        -------
        str
            The cause, with the distinct positions (or still poses) and the seconds they
            span, then where to move the plate.
        """
        s = self.samples
        if self.per_scan:
            n, seconds = distinct_positions(s.volts), s.seconds
        else:
            n = len(s)
            seconds = (int(s.stamp_ns[-1]) - int(s.stamp_ns[0])) / 1e9 if n > 1 else 0.0
        return motion.too_little_motion(n, seconds, why, self.advice, still=not self.per_scan)


#: the chi-square bounds' level as the docs write it ("99.9 %")
_BOUND = f"{100 * (1 - closure.CHI2_TAIL):g} %"


class Check:
    """One acceptance gate: its name, where it applies, what it measures, how it is judged.

    A subclass sets :attr:`name` (its :class:`~loopcal.daemon.worker.gates.gate.Gate`'s)
    and :attr:`before_fit`, and defines :meth:`documented` and :meth:`measure`;
    :meth:`applies` says for which fits.
    """

    #: the gate's name, as its Gate carries it
    name: ClassVar[str]
    #: judged on the samples before any fit (a failure stops the worker there)
    before_fit: ClassVar[bool] = False
    #: judges whether the motion told the free parameters apart: when it fails, the other
    #: failed gates of its stage follow from it, and advise more motion (:func:`measure_gates`)
    judges_motion: ClassVar[bool] = False

    def documented(self) -> tuple[str, ...]:
        """The gate's limits as docs/calibration.md's table of gates writes them.

        Returns
        -------
        tuple of str
            Texts its row there must contain (tests/daemon/worker/test_gates.py checks).
        """
        raise NotImplementedError

    def applies(self, ctx: GateContext) -> bool:
        """Whether the gate judges this context: by default, once there is a fit.

        Parameters
        ----------
        ctx : GateContext
            The samples, and the fit if there is one.

        Returns
        -------
        bool
        """
        return ctx.fit is not None

    def measure(self, ctx: GateContext) -> Gate:
        """The gate's verdict on the context.

        Parameters
        ----------
        ctx : GateContext
            The samples, and the fit if there is one; :meth:`applies` to it.

        Returns
        -------
        Gate
        """
        raise NotImplementedError


class Poses(Check):
    """``poses``: enough motion, every channel moving (still poses, or distinct positions of
    every scan)."""

    name, before_fit, judges_motion = "poses", True, True

    def documented(self) -> tuple[str, ...]:
        n = motion.MIN_POSES
        return (f"at least {n} distinct positions ({POSITION_CELL_V:g}-V cells",
                f"at least {n} still poses", f"within {motion.BARELY_MOVED_V:g} V",
                f"under {motion.MIN_CHANNEL_RANGE_V:g} V")  # fmt: skip

    def applies(self, ctx: GateContext) -> bool:
        return ctx.positions

    def measure(self, ctx: GateContext) -> Gate:
        s = ctx.samples
        return motion.scans_gate(s.volts, s.seconds) if ctx.per_scan else motion.poses_gate(s.volts)


class Converged(Check):
    """``converged``: the identification converged (it also reports one that raised)."""

    name = "converged"

    def documented(self) -> tuple[str, ...]:
        return ("Levenberg-Marquardt converged",)

    def applies(self, ctx: GateContext) -> bool:
        return ctx.fit is not None or ctx.error is not None

    def measure(self, ctx: GateContext) -> Gate:
        if ctx.fit is None:
            exc = ctx.error
            return Gate("converged", False, type(exc).__name__, "converged", str(exc),
                        advice_text(ctx.advice))  # fmt: skip
        return parameters.converged_gate(ctx.fit.converged, ctx.fit.message)


class Condition(Check):
    """``condition``: the scaled Jacobian's condition number."""

    name, judges_motion = "condition", True

    def documented(self) -> tuple[str, ...]:
        return (f"condition number ≤ {CONDITION_OK:g}",)

    def measure(self, ctx: GateContext) -> Gate:
        return parameters.condition_gate(ctx.fit.indices.condition, ctx.advice)


class MinSingular(Check):
    """``min_singular``: the scaled Jacobian's smallest singular value."""

    name, judges_motion = "min_singular", True

    def documented(self) -> tuple[str, ...]:
        return (f"minimum singular value ≥ {parameters.MIN_SINGULAR:g}",)

    def measure(self, ctx: GateContext) -> Gate:
        return parameters.min_singular_gate(ctx.fit.indices.min_singular, ctx.advice)


class Noise(Check):
    """``noise``: the fit's noise against what the samples' own scatter predicts."""

    name = "noise"

    def documented(self) -> tuple[str, ...]:
        return (f"at most {closure.NOISE_RATIO:g} ×",)

    def measure(self, ctx: GateContext) -> Gate:
        return closure.noise_gate(ctx.fit.sigma_volts, ctx.expected_noise, still=not ctx.per_scan)


class Averaging(Check):
    """``averaging``: a fit on every scan only; its misfit averages down as noise does."""

    name = "averaging"

    def documented(self) -> tuple[str, ...]:
        return (f"{closure.AVERAGING_S:g}-s windows",
                f"{closure.AVERAGING_MARGIN:g} × its {_BOUND} chi-square bound")  # fmt: skip

    def applies(self, ctx: GateContext) -> bool:
        return ctx.fit is not None and ctx.per_scan

    def measure(self, ctx: GateContext) -> Gate:
        # the misfit over windows of AVERAGING_S of consecutive fitted scans
        s, fit = ctx.samples, ctx.fit
        used = ctx.chosen[fit.used]
        misfit = closure_misfit(s.volts[used], fit.rotations, fit.params)
        rows = s.rows[used, 0]
        stride = getattr(s, "stride", 1)
        run_starts = np.flatnonzero(np.diff(rows, prepend=rows[:1] - 2 * stride) != stride)
        window = max(2, round(closure.AVERAGING_S * s.scan_rate_hz / stride))
        return closure.averaging_gate(*averaging_ratio(misfit, run_starts, window))


class Gains(Check):
    """``gains``: a fit on every scan with gains held fixed only; none would fit better."""

    name = "gains"

    def documented(self) -> tuple[str, ...]:
        return (f"within its {_BOUND} chi-square bound",)

    def applies(self, ctx: GateContext) -> bool:
        return ctx.fit is not None and ctx.per_scan and bool(self._fixed(ctx))

    @staticmethod
    def _fixed(ctx: GateContext) -> list[str]:
        return [n for n in GROUPS["gains"] if n in ctx.model.fixed]

    def measure(self, ctx: GateContext) -> Gate:
        # the score test of the fixed gains at the fit: unit weights, so the statistic is
        # in V^2 and the changes per 1/V
        names, fit = self._fixed(ctx), ctx.fit
        V = ctx.samples.volts[ctx.chosen[fit.used]]
        E = np.zeros((len(NAMES), len(names)))
        E[[INDEX[n] for n in names], np.arange(len(names))] = 1.0
        t = score_test(V, np.ones_like(V), fit.rotations, fit.params, fit.model.tie_matrix, E)
        sigma = fit.sigma_volts
        return closure.gains_gate(names, t.statistic / sigma**2, t.change, t.std * sigma)


class Holdout(Check):
    """``holdout``: the samples kept out of the checked fit close their loops as predicted."""

    name = "holdout"

    def documented(self) -> tuple[str, ...]:
        return (f"{closure.HOLDOUT_MARGIN:g} × the {_BOUND} chi-square bound",)

    def measure(self, ctx: GateContext) -> Gate:
        blocks = len(np.unique(ctx.samples.block[ctx.held_out])) if ctx.per_scan else None
        return closure.holdout_gate(ctx.holdout_z, blocks=blocks)


class Plausible(Check):
    """``plausible``: no parameter moved further than a refit or a tolerance explains."""

    name = "plausible"

    def documented(self) -> tuple[str, ...]:
        lim = parameters.CHANGE_LIMITS
        return (f"no offset moves more than {lim['offset']:g} mm",
                f"no geometry more than {lim['geometry']:g} mm",
                f"no gain more than {100 * lim['gain']:g} %",
                f"within {parameters.PLAUSIBLE_SIGMA:g} standard deviations")  # fmt: skip

    def measure(self, ctx: GateContext) -> Gate:
        return parameters.plausible_gate(list(ctx.model.free), ctx.start, ctx.fit.params,
                                         std=ctx.fit.std, imprecise=ctx.too_little_motion)


class Precision(Check):
    """``precision``: every identified parameter's standard deviation within its limit."""

    name = "precision"

    def documented(self) -> tuple[str, ...]:
        p = parameters.PRECISION
        return (f"≤ {p['mm']:g} mm ({p['mm/V']:g} mm/V)",)

    def measure(self, ctx: GateContext) -> Gate:
        return parameters.precision_gate(
            list(ctx.model.free), ctx.fit.std, ctx.advice,
            seconds=ctx.samples.seconds if ctx.per_scan else None, limit_mm=ctx.precision_mm,
        )  # fmt: skip


#: every acceptance gate, in the order the worker reports them
GATES: tuple[Check, ...] = (Poses(), Converged(), Condition(), MinSingular(), Noise(),
                            Averaging(), Gains(), Holdout(), Plausible(), Precision())  # fmt: skip


def measure_gates(ctx: GateContext, *, before_fit: bool) -> list[Gate]:
    """The verdicts of the gates of one stage that apply to the context, in order.

    Parameters
    ----------
    ctx : GateContext
        The samples, and the fit if there is one.
    before_fit : bool
        The gates judged on the samples before any fit (``poses``), else those after it.

    Returns
    -------
    list of Gate
        One per gate of :data:`GATES` of that stage that :meth:`Check.applies`. When a
        gate that judges the motion (:attr:`Check.judges_motion`) failed, every other
        failed gate's advice is :meth:`GateContext.too_little_motion` instead of its own:
        its figure follows from that, not from the mechanism.
    """
    checks = [c for c in GATES if c.before_fit == before_fit and c.applies(ctx)]
    gates = [c.measure(ctx) for c in checks]
    weak = [g.name for c, g in zip(checks, gates, strict=True) if c.judges_motion and not g.passed]
    if not weak:
        return gates
    advice = None  # made once, if another gate failed
    for k, (c, g) in enumerate(zip(checks, gates, strict=True)):
        if not g.passed and not c.judges_motion:
            advice = advice or ctx.too_little_motion(f"{', '.join(weak)} failed")
            gates[k] = replace(g, advice=advice)
    return gates
