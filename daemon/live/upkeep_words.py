"""What the upkeep shows while it runs: its part of the status line, and its metrics.

:class:`Words` is a part of :class:`~loopcal.daemon.live.upkeep.Upkeep` (a mixin).

Both say the same things as ``loopcal upkeep status`` (from the kept record, when the
daemon does not run): a proposal pending, a change in progress (the offsets told, or the
candidates and the move that would tell them apart), the baseline's progress, or that
nothing changed. While a change stands the config in force is known to be wrong, and the
status line and the metrics say so until it is fixed or gone.
"""

from __future__ import annotations

import time
from typing import Any

from ..config.controller import ControllerConfig
from ..times import time_or
from ..worker.offsets import calibrated, offset_std
from .changes import BASELINE_SEGMENTS, OffsetTests
from .upkeep_state import UpkeepRecord


class Words:
    """The upkeep's words (module docstring); the attributes are the upkeep's."""

    mode: str
    record: UpkeepRecord | None
    tests: OffsetTests | None
    advice: str
    state: Any  # UpkeepState
    reference: ControllerConfig
    unsure: tuple  # ((name, std mm), ...): Acts.vouch

    def change_words(self) -> str:
        """The change in progress in words ("" when none stands)."""
        rec = self.record
        ch = None if rec is None else rec.change
        if ch is None or not ch.stood or self.tests is None:
            return ""
        since = time_or(ch.since_ns)
        if ch.names:
            doing = self.state.change or "identifying it from the robot's motion"
            return f"LOOPS OPEN since {since}: {self.tests.words()}: {doing}"
        told = f"not told apart yet: {self.advice}" if self.advice else "which offset, not told yet"
        return f"LOOPS OPEN since {since}: {self.tests.words()}, {told}"

    def status(self) -> str:
        """The upkeep's part of the status line."""
        st, rec = self.state, self.record
        change = self.change_words()
        if st.pending is not None:
            names = ", ".join(st.pending.values)
            since = time_or(st.pending_since_ns)
            out = f"RECALIBRATION PROPOSED ({names}) since {since}: loopcal upkeep apply"
            return f"{out}; upkeep: {change}" if change else out
        if self.mode == "off":
            return "upkeep off"
        if rec is not None and rec.uncalibrated:
            return (
                "upkeep: the loops do not close at this config, which loopcal never "
                "calibrated: calibrate with loopcal session"
            )
        if change:
            return f"upkeep: {change}"
        if rec is not None and rec.creeping:
            return (
                f"upkeep ({self.mode}): {' or '.join(rec.creeping)} CREEPS away from the "
                "config (fixed each time it reaches the threshold)"
            )
        if st.change:
            return f"upkeep: {st.change}"
        if self.unsure:
            return (
                f"upkeep ({self.mode}): OFFSETS UNCERTAIN: "
                + ", ".join(f"{n} +- {s:.3f} mm" for n, s in self.unsure)
                + ": calibrate with loopcal session"
            )
        if rec is not None and rec.baseline.segments < BASELINE_SEGMENTS:
            return (
                f"upkeep ({self.mode}): nothing changed (baseline {rec.baseline.segments}/"
                f"{BASELINE_SEGMENTS} segments)"
            )
        return f"upkeep ({self.mode}): nothing changed"

    def metrics(self) -> list:
        """Prometheus families: a proposal pending and its age; a change standing, whether its
        offsets are told apart, its age and its candidates' shifts; the offsets' std in the
        config and whether it vouches for them; the baseline's segments; fits and their CPU
        time; proposals, writes, withdrawals and refusals."""
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        st, rec = self.state, self.record
        pending = st.pending is not None
        ch = None if rec is None else rec.change
        standing = ch is not None and ch.stood and self.tests is not None
        out = [
            GaugeMetricFamily(
                "loopcal_upkeep_proposal_pending",
                "1 while a recalibration the daemon proposed waits to be applied or discarded",
                value=1.0 if pending else 0.0,
            ),
            GaugeMetricFamily(
                "loopcal_upkeep_change",
                "1 while the loops do not close at the "
                "controller config since a change the upkeep has not fixed",
                value=1.0 if standing else 0.0,
            ),
            GaugeMetricFamily(
                "loopcal_upkeep_change_unattributed",
                "1 while such a change stands and the robot's motion cannot tell which "
                "offset moved",
                value=1.0 if standing and not ch.names else 0.0,
            ),
            GaugeMetricFamily(
                "loopcal_upkeep_offsets_uncertain",
                "1 while the config in force knows an offset too poorly to vouch for the "
                "threshold (3 std reach it): calibrate with loopcal session",
                value=1.0 if self.unsure else 0.0,
            ),
            GaugeMetricFamily(
                "loopcal_upkeep_baseline_segments",
                f"unchanged segments in the upkeep's baseline (it holds at {BASELINE_SEGMENTS})",
                value=0.0 if rec is None else rec.baseline.segments,
            ),
        ]
        if pending:
            out.append(
                GaugeMetricFamily(
                    "loopcal_upkeep_proposal_age_seconds",
                    "seconds since the pending proposal was written",
                    value=max(0.0, (time.time_ns() - st.pending_since_ns) / 1e9),
                )
            )
        cand = GaugeMetricFamily(
            "loopcal_upkeep_candidate_shift_mm",
            "each explanation of the "
            "change not ruled out (candidate 1 the likeliest): its shift of "
            "an offset, mm",
            labels=["candidate", "offset"],
        )
        if standing:
            out.append(
                GaugeMetricFamily(
                    "loopcal_upkeep_change_age_seconds",
                    "seconds since the change began (the scans' stamps)",
                    value=max(0.0, (time.time_ns() - ch.since_ns) / 1e9),
                )
            )
            for k, c in enumerate(self.tests.candidates, 1):
                for name, shift in zip(c.names, c.shift_mm, strict=True):
                    cand.add_metric([str(k), name], float(shift))
        out.append(cand)
        if self.mode != "off" and calibrated(self.reference):
            std = GaugeMetricFamily(
                "loopcal_upkeep_offset_std_mm",
                "each offset's standard deviation in the config in force (or the proposal "
                "pending), the errors of the offsets held through its fixes counted, mm",
                labels=["offset"],
            )
            for name, value in offset_std(self.reference).items():
                std.add_metric([name], value)
            out.append(std)
        for name, doc, value in (
            ("loopcal_upkeep_fits", "upkeep fits run (screens and refits)", st.fits),
            ("loopcal_upkeep_fit_cpu_seconds", "CPU time of the upkeep's fits, s", st.fit_cpu_s),
            ("loopcal_upkeep_proposals", "recalibrations proposed", st.proposals),
            ("loopcal_upkeep_writes", "recalibrations written to the config", st.written),
            ("loopcal_upkeep_withdrawals", "proposals withdrawn", st.withdrawn),
            (
                "loopcal_upkeep_refusals",
                "changes the motion did not identify, or whose fix could not be written",
                st.refused,
            ),
        ):
            out.append(CounterMetricFamily(name, doc, value=value))
        return out
