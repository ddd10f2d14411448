"""What the upkeep does about a change: say it, propose or write its fix, take a proposal back.

:class:`Acts` is a part of :class:`~loopcal.daemon.live.upkeep.Upkeep` (a mixin): its
methods act on the upkeep's change and speak through its ``emit`` (the recorder's events):

- :meth:`~Acts.announce`: a change stands (``offset_change``): the offsets told apart, or
  the candidates the motion cannot yet tell apart, each one's shift, and the move that
  would tell them (the config in force is wrong: never silence);
- :meth:`~Acts.act`: a refit every gate passed: in ``propose`` mode the complete config
  beside the one in force (``recalibration_proposed``), in ``write`` mode the config
  itself through the path a person's calibration takes (``recalibrated``: the previous
  version kept), in ``report`` mode only told. The change's own scans, seen at the new
  values, are then the baseline (:meth:`~Acts.after_act`). A write or proposal that fails
  (a full disk, a config edited meanwhile) keeps the change: it is said once, and tried
  again with the next segment;
- :meth:`~Acts.withdraw`, :meth:`~Acts.set_aside`, :meth:`~Acts.check_pending`: a pending
  proposal that later scans contradict, that can no longer be applied, or that a person
  applied or discarded.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import replace
from typing import Any

import numpy as np

from loopcal.calibration.parameters import INDEX

from ..config.controller import ControllerConfig, ControllerConfigError, load_controller_config
from ..events import Level
from ..times import now_text, time_or
from ..worker.offsets import (
    OFFSETS,
    UNSURE_SIGMAS,
    OffsetFit,
    config_cov,
    fixed_cov,
    unsure_offsets,
)
from ..worker.proposal import (
    Proposal,
    discard_proposal,
    proposal_path,
    proposal_provenance,
    read_proposal,
    write_proposal,
)
from ..worker.writeback import write_back
from .changes import (
    LIMIT,
    Normal,
    OffsetTests,
    Reference,
    offset_tests,
    steplike,
    trend,
)
from .upkeep_state import TREND_SEGMENTS, Change, Keeper, UpkeepRecord, reference_digest

log = logging.getLogger(__name__)

#: segments since the last action a creep needs to be told from a step
TREND_MIN_SEGMENTS = 4

#: what each mode does once a change is identified, for the announcement
WILL = {
    "write": "it will be written into the controller config once every gate passes",
    "propose": "a recalibration will be proposed once every gate passes",
    "report": "a recalibration would be proposed once every gate passes",
}


class Acts:
    """The upkeep's actions (module docstring); the attributes are the upkeep's."""

    mode: str
    emit: Any
    controller: ControllerConfig
    reference: ControllerConfig
    record: UpkeepRecord | None
    tests: OffsetTests | None
    advice: str
    keeper: Keeper
    directory: str | None
    target_mm: float
    threshold_mm: float
    state: Any  # UpkeepState
    _recent: Any  # deque of the latest segments
    min_interval_ns: int
    #: the offsets said known too poorly to vouch for, with their std: ((name, mm), ...)
    unsure: tuple = ()

    def vouch(self) -> None:
        """Say when the reference (the config in force, or the proposal pending) knows an
        offset too poorly to vouch for the threshold
        (:func:`~loopcal.daemon.worker.offsets.unsure_offsets`), as fixes from motion that
        cannot tell the four apart leave them
        (:func:`~loopcal.daemon.worker.offsets.fixed_cov`): their loops close while each
        may be off by more than they show. ``offsets_uncertain``, said again whenever what
        it would say changes; a calibration from motion that tells them apart
        (``loopcal session``) knows them again. A config loopcal never calibrated is
        health's to say (``loops_open``)."""
        said = self.unsure
        self.unsure = (
            () if self.mode == "off" else unsure_offsets(self.reference, self.threshold_mm)
        )
        if not self.unsure or self.unsure == said:
            return
        words = ", ".join(f"{n} +- {s:.3f} mm" for n, s in self.unsure)
        self.emit(
            "offsets_uncertain",
            Level.WARNING,
            f"upkeep: the controller config knows {words} only (std): "
            f"{UNSURE_SIGMAS:g} std reach the {self.threshold_mm:g} mm threshold, so its "
            "loops may close while an offset is that far off. Fixes of one offset from "
            "motion that cannot tell the four apart carry the others' errors into it; "
            "calibrate with loopcal session (motion that tells them apart) to know them "
            "again",
            std=dict(self.unsure),
            threshold_mm=self.threshold_mm,
        )

    def with_values(
        self, values: dict[str, float], std: dict[str, float], cov: np.ndarray | None = None
    ) -> ControllerConfig:
        """The config in force with ``values`` (and their ``std``, the offsets' ``cov``) in
        place of its own."""
        params = np.array(self.controller.params, dtype=float)
        for n, v in values.items():
            params[INDEX[n]] = v
        prov = proposal_provenance(self.controller, values, std, {}, cov)
        return replace(self.controller, params=params, provenance=prov)

    def announce(self, ch: Change) -> None:
        """Say, once, that the loops no longer close at the config, and what is known."""
        tests = self.tests
        if ch.announced or tests is None:
            return
        ch.announced = True
        since = time_or(ch.since_ns)
        if ch.names:
            best = tests.candidates[0]
            std = ", ".join(f"+-{s:.2f}" for s in best.std_mm)
            text = (
                f"upkeep: the loops no longer close at the controller config since {since}: "
                f"{best.words()} ({std}); {WILL[self.mode]}"
            )
        else:
            text = (
                f"upkeep: the loops no longer close at the controller config since {since}, "
                "and the robot's motion so far cannot tell which offset moved: "
                f"{tests.words()}; to tell them apart, {self.advice} (the upkeep fixes it "
                "as soon as the motion tells)"
            )
        self.emit(
            "offset_change",
            Level.WARNING,
            text,
            since_ns=ch.since_ns,
            names=list(ch.names),
            candidates=[c.as_json() for c in tests.candidates],
            advice=self.advice,
            mode=self.mode,
        )

    def refuse(self, ch: Change, end_ns: int, why: str, level: Level, message: str) -> None:
        """Say that a change is not (yet) fixed, and why."""
        rec = self.record
        assert rec is not None
        self.state.refused += 1
        rec.refusals += 1
        rec.last_refusal = {"ns": int(end_ns), "names": list(ch.names), "why": why}
        self.emit(
            "recalibration_refused",
            level,
            message,
            names=list(ch.names),
            since_ns=ch.since_ns,
            refusal=why,
        )

    def _table(self, fit: OffsetFit, ch: Change, since: int, until: int) -> dict[str, Any]:
        base = {n: float(self.controller.params[INDEX[n]]) for n in fit.changed}
        values = fit.values()
        return {
            "mode": self.mode,
            "change_since_ns": int(ch.since_ns),
            "change_since_utc": time_or(ch.since_ns),
            "window_since_ns": int(since),
            "window_until_ns": int(until),
            "proposed_ns": time.time_ns(),
            "proposed_utc": now_text(),
            "shift_mm": {n: round(values[n] - base[n], 5) for n in fit.changed},
            "scans": int(fit.scans),
            "target_mm": self.target_mm,
            "threshold_mm": self.threshold_mm,
            "gates": {g.name: bool(g.passed) for g in fit.gates},
            "recordings": self.directory or "",
        }

    def act(self, fit: OffsetFit, ch: Change, since: int, until: int) -> None:
        """Propose, write or report an accepted refit (module docstring). Its std counts
        what the offsets held at the config carry into it (:func:`fixed_cov`), not only
        the scans' noise."""
        values, scans_std = fit.values(), fit.std()
        cov = fixed_cov(config_cov(self.reference), ch.rest.N, fit.changed, scans_std)
        std = {n: float(np.sqrt(cov[i, i])) for i, n in enumerate(OFFSETS) if n in values}
        table = self._table(fit, ch, since, until)
        words = ", ".join(
            f"{n} {values[n]:.4f} mm ({table['shift_mm'][n]:+.3f} +- {std[n]:.3f}; the "
            f"scans' own +- {scans_std[n]:.3f})"
            for n in fit.changed
        )
        details: dict[str, Any] = dict(
            values={n: round(v, 6) for n, v in values.items()},
            std={n: round(s, 6) for n, s in std.items()},
            scans_std={n: round(s, 6) for n, s in scans_std.items()},
            shift_mm=table["shift_mm"],
            since_ns=ch.since_ns,
            window_since_ns=since,
            window_until_ns=until,
            scans=table["scans"],
            gates=table["gates"],
        )
        delta = np.zeros(4)
        for n, v in values.items():
            delta[OFFSETS.index(n)] = v - float(self.reference.params[INDEX[n]])
        written = None
        try:
            if self.mode == "report":  # what it would propose (loopcal check), nothing written
                self.state.reported.append({"names": list(fit.changed), **details})
                kind, path = "recalibration_proposed", ""
                text = (
                    f"upkeep would propose {words}, changed since "
                    f"{table['change_since_utc']}, every gate passed"
                )
            elif self.mode == "propose":
                path = str(write_proposal(self.controller, values, std, table, cov))
                self.state.pending = read_proposal(self.controller)
                self.state.pending_since_ns = table["proposed_ns"]
                kind = "recalibration_proposed"
                text = (
                    f"upkeep: a recalibration is proposed in {path}: {words}, changed since "
                    f"{table['change_since_utc']}, every gate passed; review it (loopcal "
                    "upkeep status) and apply it (loopcal upkeep apply) or discard it"
                )
            else:
                params = np.array(self.controller.params, dtype=float)
                for n, v in values.items():
                    params[INDEX[n]] = v
                prov = proposal_provenance(self.controller, values, std, table, cov)
                out = write_back(self.controller, params, prov)
                written = load_controller_config(out.path)
                path, kind = str(out.path), "recalibrated"
                details["previous"] = str(out.backup)
                text = (
                    f"upkeep: wrote {words} into {out.path} (changed since "
                    f"{table['change_since_utc']}; every gate passed, as a person's "
                    f"calibration needs; the previous version kept as {out.backup})"
                )
        except ControllerConfigError as exc:
            failed = "written" if self.mode == "write" else "proposed"
            if not ch.refused:  # said once; tried again with the next segment
                ch.refused = True
                self.refuse(
                    ch,
                    until,
                    str(exc),
                    Level.ERROR,
                    f"upkeep: {words} identified but not {failed}: {exc}; trying again with "
                    "the next scans",
                )
            self.state.change = f"identified but not {failed}: {exc}"
            return
        if kind == "recalibrated":
            self.state.written += 1
        else:
            self.state.proposals += 1
        self.emit(kind, Level.WARNING, text, path=path, **details)
        rec = self.record
        assert rec is not None
        rec.last_action = {"kind": kind, "ns": time.time_ns(), "path": path, **details}
        self.after_act(delta, values, std, cov, ch, until, written)

    def after_act(
        self,
        delta: np.ndarray,
        values: dict[str, float],
        std: dict[str, float],
        cov: np.ndarray,
        ch: Change,
        until: int,
        written: ControllerConfig | None,
    ) -> None:
        """The change was proposed (or ``written``, the config now in force): the reference
        moves to ``values`` (``delta`` (4,) from where it was), and the change's own scans,
        seen at them, are its baseline: a second change minutes later is told at once."""
        rec = self.record
        assert rec is not None
        if written is not None:
            self.controller = self.reference = written
        else:
            self.reference = self.with_values(values, std, cov)
        going = self.creeps_on(delta, ch, until)
        for n in values:
            rec.acted[n] = [int(until), round(float(delta[OFFSETS.index(n)]), 6), ch.gradual]
        rec.reference = reference_digest(self.reference.params)
        rec.config_sha256 = self.controller.sha256
        rec.baseline = ch.rest.shifted(delta - ch.point)
        rec.change, rec.trend = None, []
        self._recent.clear()  # tested at the old values
        self.tests, self.advice, self.state.change = None, "", ""
        if going:
            self.warn_creeps_on(rec, going, written is not None)
        self.vouch()
        if self.mode != "report":
            self.keeper.save(rec, until)

    def creeps_on(self, delta: np.ndarray, ch: Change, until: int) -> dict[str, float]:
        """The offsets of a fix (``delta`` (4,) mm from the reference) that creep on: said
        to creep (:meth:`warn_creep`) and still growing the fix's way over the trend, or
        fixed the same way at most 1.5 ``min_interval`` before ``until`` and said to creep
        or moved little by little (this change or that fix's): their rates, mm/s."""
        rec = self.record
        assert rec is not None
        out = {}
        if rec.creeping and len(rec.trend) >= 2 * TREND_MIN_SEGMENTS:
            slope = trend(*rec.trend_arrays())[0]
            for n in rec.creeping:
                i = OFFSETS.index(n)
                if delta[i] * slope[i] > 0:
                    out[n] = float(slope[i])
        for n, last in rec.acted.items():
            shift, dt = float(delta[OFFSETS.index(n)]), (until - last[0]) / 1e9
            if shift and 0 < dt <= 1.5 * self.min_interval_ns / 1e9 and shift * last[1] > 0:
                if ch.gradual or last[2] or n in rec.creeping:
                    out[n] = shift / dt
        return out

    def warn_creeps_on(self, rec: UpkeepRecord, rates: dict[str, float], written: bool) -> None:
        """Say, with the fix, that the offsets ``rates`` (mm/s) creep on: the values just
        fixed will be off by the threshold again before the next fix (at most every
        ``min_interval``), until the creep stops (``offset_change``, ``creeping``)."""
        rec.creeping = list(rates)
        fixed = "written" if written else "proposed"
        words = " and ".join(f"{n} still creeps {r * 60:+.3f} mm/min" for n, r in rates.items())
        soon = min(self.threshold_mm / abs(r) for r in rates.values())
        self.emit(
            "offset_change",
            Level.WARNING,
            f"upkeep: {words}: a creep goes on, and the values just {fixed} will be "
            f"{self.threshold_mm:g} mm off again in about {soon / 60:.0f} min, and are fixed "
            f"again at most every {self.min_interval_ns / 60e9:g} min until the creep stops "
            "(check that LVDT's core and mounting)",
            names=[],
            candidates=[
                {"names": [n], "shift_mm": [0.0], "rate_mm_min": round(r * 60, 5)}
                for n, r in rates.items()
            ],
            advice="",
            mode=self.mode,
            creeping=True,
        )

    def creeping(self, name: str, shift: float, ch: Change, end_ns: int) -> bool:
        """Whether ``name``, fixed less than ``min_interval`` ago, creeps: it moved on while
        its change stood, or it moved on the same way as the last fix (``shift`` mm from
        the config) and it is said to creep, or moved little by little, this change or
        that fix's (no one segment told it): a creep goes on one way, a swapped sensor's
        offset jumps, either way."""
        rec = self.record
        assert rec is not None
        last = rec.acted.get(name)
        if last is None or end_ns - last[0] >= self.min_interval_ns:
            return False
        little = ch.gradual or bool(last[2]) or name in rec.creeping
        return bool(ch.steps) or (little and shift * last[1] > 0)

    def warn_creep(self, rec: UpkeepRecord) -> None:
        """An offset whose shift from the config grows steadily (a slope at
        :data:`~.changes.LIMIT` over the segments since the reference took force or the
        last fix, and a straight line tells it better than a step) and has reached half the
        threshold is said before it reaches it (``offset_change``, ``creeping``): once,
        until no shift grows any more (a fix that finds it going on says so itself:
        :meth:`warn_creeps_on`)."""
        if len(rec.trend) < 2 * TREND_MIN_SEGMENTS:
            return
        t, shift, std = rec.trend_arrays()
        slope, now, T = trend(t, shift, std)
        going = (T >= LIMIT) & (np.abs(now) >= self.threshold_mm / 2) & (slope * now > 0)
        going &= [not (g and steplike(t, shift[:, i], std[:, i])) for i, g in enumerate(going)]
        if rec.creeping:  # said once while it creeps: until no shift grows at all
            # it stopped (over a full trend: the few segments after a fix cannot tell):
            # what it left under the threshold is settled
            if T.max() < 4.0 and len(rec.trend) >= TREND_SEGMENTS:
                rec.settle, rec.creeping = rec.creeping, []
            return
        if not going.any():
            return
        # which one: the latest segments' explanations not ruled out (a single offset each)
        recent = sum((n for _, _, n in self._recent), Normal())
        told = offset_tests(recent, Reference(np.zeros(4), np.zeros((4, 4))), threshold_mm=0)
        names = [c.names[0] for c in told.candidates if len(c.names) == 1]
        names = names or [OFFSETS[i] for i in np.argsort(-T) if going[i]]
        rec.creeping = names
        words = " or ".join(
            f"{n} {now[OFFSETS.index(n)]:+.3f} mm, growing "
            f"{slope[OFFSETS.index(n)] * 60:+.3f} mm/min"
            for n in names
        )
        self.emit(
            "offset_change",
            Level.WARNING,
            f"upkeep: an offset creeps away from the controller config: {words}; a creep is "
            "a sensor's mounting giving way (check that LVDT's core): the upkeep fixes it "
            f"each time it reaches {self.threshold_mm:g} mm",
            since_ns=int(t[0]),
            names=[],
            candidates=[
                {
                    "names": [n],
                    "shift_mm": [round(float(now[OFFSETS.index(n)]), 5)],
                    "rate_mm_min": round(float(slope[OFFSETS.index(n)] * 60), 5),
                }
                for n in names
            ],
            advice="",
            mode=self.mode,
            creeping=True,
        )

    def withdraw(self, test: OffsetTests, start_ns: int) -> None:
        """Later scans contradict the pending proposal: take it back."""
        st = self.state
        old: Proposal = st.pending
        try:
            aside = discard_proposal(self.controller)
        except OSError as exc:
            log.error("upkeep: cannot withdraw %s: %s", old.path, exc)
            return
        st.pending, st.withdrawn = None, st.withdrawn + 1
        b = int(np.argmax(test.statistic))
        self.emit(
            "recalibration_withdrawn",
            Level.WARNING,
            f"upkeep: the proposal {old.path} is withdrawn (kept as {aside}): the scans since "
            f"{time_or(start_ns)} disagree with it ({OFFSETS[b]} {test.shift_mm[b]:+.3f} mm "
            "from its values)",
            path=str(old.path),
            aside=str(aside),
            names=list(old.values),
            since_ns=start_ns,
        )

    def set_aside(self, why: str) -> None:
        """A proposal beside the config that can no longer be applied (the config changed
        since, or it was damaged): renamed aside, said once, so that nobody applies it."""
        try:
            aside = discard_proposal(self.controller)
        except OSError as exc:
            log.error(
                "upkeep: the proposal beside %s cannot be set aside: %s", self.controller.path, exc
            )
            return
        self.state.withdrawn += 1
        self.emit(
            "recalibration_withdrawn",
            Level.WARNING,
            f"upkeep: the proposal beside {self.controller.path} is withdrawn (kept as "
            f"{aside}): {why}",
            path=str(proposal_path(self.controller.path)),
            aside=str(aside),
            names=[],
            since_ns=time.time_ns(),
        )

    def check_pending(self) -> None:
        """A pending proposal a person applied or discarded is no longer pending; a
        discarded one's values stay the reference (never two proposals for one change)."""
        st = self.state
        if st.pending is None or self.controller.path is None:
            return
        if not os.path.lexists(proposal_path(self.controller.path)):
            log.info("upkeep: the proposal %s was taken away", st.pending.path)
            st.pending = None
