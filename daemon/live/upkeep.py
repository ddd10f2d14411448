"""Upkeep: the daemon recalibrates what changed, from the robot's own motion.

Scans -> segments -> screen -> change -> refit -> gates -> proposal (or config). The
recorder feeds every scan (:meth:`Upkeep.feed`, from the analysis thread); a worker thread
of its own, at the lowest CPU priority, does the rest, so that neither the recording nor
the other observers ever wait for a fit.

1. **Test.** Every ``[upkeep].segment`` of scans (15 s), loop closure on every usable scan (moving
   or still, the channel skew corrected) is summed into the four offsets' normal
   equations at the reference (:mod:`.changes`): the controller config in force, with the
   values of a pending proposal in place of its own (so that a change is proposed once).
   Each segment is tested against the baseline, the first unchanged segments since the
   (re)start: has any offset moved by at least ``threshold_mm``, at a false-alarm
   probability of 1e-8 per segment?
2. **Change.** A segment that moved opens a candidate change; the next segment that tells
   anything either moved too (the change stands) or not (a blip: dropped, nothing said).
   The change began within the first segment; that segment is left out of what follows
   (a few scans from before the change would bias it). Which offsets: the segments after
   it, summed, point at one sensor (or two) clearly enough (:func:`.changes.offset_tests`).
3. **Refit.** While the change stands, each new segment refits the named offsets on every
   scan after the first segment (at most the latest :data:`FIT_WINDOW_S`, so that a creep
   is fitted where it is now) with the gates that apply
   (:func:`~loopcal.daemon.worker.offsets.refit_offsets`): the precision at
   ``target_mm``, the holdout, the averaging, the plausibility, the fit's own. Motion that
   does not make the change identifiable within :data:`REFUSE_AFTER_S` is refused, said
   once (``recalibration_refused``), and the refit goes on with the motion that comes.
4. **Act.** Accepted, and no offset named was proposed or written less than
   ``min_interval_s`` ago: in ``propose`` mode the complete config beside the one in force
   (:func:`~loopcal.daemon.worker.proposal.write_proposal`, event
   ``recalibration_proposed``); in ``write`` mode the config itself, through the path a
   person's calibration takes (:func:`~loopcal.daemon.worker.writeback.write_back`: the
   previous version kept), event ``recalibrated``; the recorder follows the new file and
   health watches against it.
5. **Withdraw.** A pending proposal that later segments contradict (a change against it
   that stands: the sensor moved on, or back) is withdrawn (renamed aside, event
   ``recalibration_withdrawn``); what the later scans show is proposed in its turn, the
   interval allowing. A proposal a person discards is not made again: its values stay the
   reference until the config changes.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from loopcal.calibration.parameters import INDEX

from ..config.controller import ControllerConfig, ControllerConfigError
from ..defaults import UPKEEP_SEGMENT_S
from ..events import Level
from ..recorder.engine import Recorder
from ..recorder.settings import RecorderSettings
from ..times import now_text, time_or
from ..worker.offsets import OFFSETS, OffsetFit, refit_offsets
from ..worker.proposal import (
    Proposal,
    discard_proposal,
    proposal_path,
    proposal_provenance,
    read_proposal,
    write_proposal,
)
from ..worker.writeback import write_back
from .changes import BASELINE_SEGMENTS, Normal, OffsetTests, offset_tests, segment_normal

log = logging.getLogger(__name__)

MODES = ("off", "propose", "write")
#: the refit uses at most the latest this many seconds of scans since the change
FIT_WINDOW_S = 120.0
#: a standing change the motion has not made identifiable for this long is refused, once
REFUSE_AFTER_S = 600.0

@dataclass
class _Change:
    """A candidate change (one segment moved) or a standing one (two or more)."""

    since_ns: int
    first: Normal  # the first segment that moved: the change may have begun inside it
    first_end_ns: int
    rest: Normal = field(default_factory=Normal)  # the segments after it
    names: list[str] = field(default_factory=list)
    refused: bool = False

    @property
    def stood(self) -> bool:
        return self.rest.segments > 0


@dataclass
class UpkeepState:
    """What the status line and the metrics show."""

    change: str = ""  # a standing change in words
    pending: Proposal | None = None
    pending_since_ns: int = 0
    fits: int = 0
    fit_cpu_s: float = 0.0
    proposals: int = 0
    written: int = 0
    withdrawn: int = 0
    refused: int = 0
    last_proposed_ns: dict[str, int] = field(default_factory=dict)
    #: in report mode, what would have been proposed (the events' details)
    reported: list[dict] = field(default_factory=list)


class Upkeep:
    """The daemon's upkeep (module docstring), an observer of the recorder's scans.

    Parameters
    ----------
    controller : ControllerConfig
        The config in force.
    emit : callable
        ``emit(kind, level, message, **details)``: the recorder's events.
    mode : {"propose", "write", "report"}
        What an accepted change does; report: nothing written, the proposal only told
        (an event, and ``state.reported``), for ``loopcal check`` on archives.
    target_mm, threshold_mm : float
        The precision a refitted offset must reach, and the smallest shift that counts, mm.
    min_interval_s : float
        The least time between two proposals (or writes) that name the same offset, s.
    segment_s : float, default 15
        How much of the scans is tested at a time, s of their stamps (``[upkeep].segment``).
    directory : path or None
        The recordings' directory, named in the proposal (for ``loopcal upkeep apply``).
    threaded : bool, default True
        Fit in a worker thread of the lowest priority; False: in :meth:`feed` (offline).
    settings : callable, optional
        The recorder's settings in force: a reload takes ``[upkeep]`` from them again (the
        mode too: off, or on once the reload brings a controller config).
    """

    name = "upkeep"

    def __init__(
        self,
        controller: ControllerConfig,
        emit: Any,
        *,
        mode: str,
        target_mm: float,
        threshold_mm: float,
        min_interval_s: float,
        segment_s: float = UPKEEP_SEGMENT_S,
        directory: os.PathLike | None = None,
        threaded: bool = True,
        settings: Callable[[], RecorderSettings] | None = None,
    ) -> None:
        if mode not in ("off", "propose", "write", "report"):
            raise ValueError(f"upkeep mode must be off, propose, write or report, got {mode!r}")
        self.mode, self.emit = mode, emit
        self.target_mm, self.threshold_mm = float(target_mm), float(threshold_mm)
        self.min_interval_ns = int(min_interval_s * 1e9)
        self.segment_ns = int(segment_s * 1e9)
        self.directory = None if directory is None else str(directory)
        self._settings = settings
        self.state = UpkeepState()
        self._rows: np.ndarray | None = None  # the scans kept: the fit window and a segment
        self._seg_start_ns: int | None = None
        self._change: _Change | None = None
        self._queue: queue.SimpleQueue | None = None
        self._thread: threading.Thread | None = None
        self._reset(controller)
        if threaded:
            self._queue = queue.SimpleQueue()
            self._thread = threading.Thread(target=self._run, name="loopcal-upkeep", daemon=True)
            self._thread.start()

    # ------------------------------------------------------------------ observer

    def feed(self, rows: np.ndarray) -> None:
        """New scans (SCAN_DTYPE rows, in order): queued for the worker (or taken now)."""
        if self._queue is None:
            self._take(rows)
        elif len(rows):
            self._queue.put(("scans", rows))

    def reload(self, controller: ControllerConfig) -> None:
        """The config in force changed (a write, an apply, an edit): start over against it."""
        if self._queue is None:
            self._reset(controller)
        else:
            self._queue.put(("reload", controller))

    def close(self, timeout: float = 10.0) -> None:
        """Stop the worker thread (what it was fitting is finished first)."""
        if self._queue is not None and self._thread is not None:
            self._queue.put(("stop", None))
            self._thread.join(timeout)

    def status(self) -> str:
        st = self.state
        if st.pending is not None:
            names = ", ".join(st.pending.values)
            since = time_or(st.pending_since_ns)
            return f"RECALIBRATION PROPOSED ({names}) since {since}: loopcal upkeep apply"
        if self.mode == "off":
            return "upkeep off"
        if st.change:
            return f"upkeep: {st.change}"
        return f"upkeep ({self.mode}): nothing changed"

    def metrics(self) -> list:
        """Prometheus families: a proposal pending and its age, fits and their CPU time,
        proposals, writes, withdrawals and refusals."""
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        st = self.state
        pending = st.pending is not None
        out = [GaugeMetricFamily("loopcal_upkeep_proposal_pending", "1 while a recalibration "
                                 "the daemon proposed waits to be applied or discarded",
                                 value=1.0 if pending else 0.0)]  # fmt: skip
        if pending:
            out.append(GaugeMetricFamily(
                "loopcal_upkeep_proposal_age_seconds",
                "seconds since the pending proposal was written", value=max(
                    0.0, (time.time_ns() - st.pending_since_ns) / 1e9)))  # fmt: skip
        for name, doc, value in (
            ("loopcal_upkeep_fits", "upkeep fits run (screens and refits)", st.fits),
            ("loopcal_upkeep_fit_cpu_seconds", "CPU time of the upkeep's fits, s", st.fit_cpu_s),
            ("loopcal_upkeep_proposals", "recalibrations proposed", st.proposals),
            ("loopcal_upkeep_writes", "recalibrations written to the config", st.written),
            ("loopcal_upkeep_withdrawals", "proposals withdrawn", st.withdrawn),
            ("loopcal_upkeep_refusals", "changes the motion did not identify", st.refused),
        ):
            out.append(CounterMetricFamily(name, doc, value=value))
        return out

    # ------------------------------------------------------------------ worker

    def _run(self) -> None:
        assert self._queue is not None
        try:  # the lowest priority for this thread alone (Linux: a thread is a task)
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        except (OSError, AttributeError):
            pass
        while True:
            what, arg = self._queue.get()
            if what == "stop":
                return
            try:
                if what == "reload":
                    self._reset(arg)
                else:
                    self._take(arg)
            except Exception:  # noqa: BLE001 - upkeep fails alone; the recording goes on
                log.exception("upkeep failed on a segment; it starts over")
                self._rows, self._change, self._seg_start_ns = None, None, None

    def _reset(self, controller: ControllerConfig) -> None:
        """Start over against ``controller`` (and the settings in force): a proposal
        beside it that is still valid stays pending (a restarted daemon does not propose
        the same change again); one that is not is set aside."""
        if self._settings is not None:
            st = self._settings()
            self.mode = upkeep_mode(st.upkeep_mode, controller)
            self.target_mm, self.threshold_mm = st.upkeep_target_mm, st.upkeep_threshold_mm
            self.min_interval_ns = int(st.upkeep_min_interval_s * 1e9)
            self.segment_ns = int(st.upkeep_segment_s * 1e9)
            self.directory = str(st.directory)
        if self.mode != "off" and controller.path is None:
            log.warning("upkeep off: it needs the robot's controller config")
            self.mode = "off"
        self.controller = controller
        self._change = None
        self._base = Normal()
        self.state.change = ""
        self.state.pending = None
        self._reference = controller
        try:
            pending = None if self.mode in ("report", "off") else read_proposal(controller)
        except ControllerConfigError as exc:
            pending = None
            self._set_aside(f"it cannot be applied: {exc}")
        if pending is not None:
            self.state.pending = pending
            since = pending.upkeep.get("proposed_ns")
            self.state.pending_since_ns = since if isinstance(since, int) else time.time_ns()
            self._reference = self._with(pending.values)

    def _set_aside(self, why: str) -> None:
        """A proposal beside the config that can no longer be applied (the config changed
        since, or it was damaged): renamed aside, said once, so that nobody applies it."""
        try:
            aside = discard_proposal(self.controller)
        except OSError as exc:
            log.error("upkeep: the proposal beside %s cannot be set aside: %s",
                      self.controller.path, exc)  # fmt: skip
            return
        self.state.withdrawn += 1
        self.emit("recalibration_withdrawn", Level.WARNING,
                  f"upkeep: the proposal beside {self.controller.path} is withdrawn (kept as "
                  f"{aside}): {why}", path=str(proposal_path(self.controller.path)),
                  aside=str(aside), names=[],
                  since_ns=time.time_ns())  # fmt: skip

    def _with(self, values: dict[str, float]) -> ControllerConfig:
        """The config in force with ``values`` in place of its own (and their std)."""
        params = np.array(self.controller.params, dtype=float)
        for n, v in values.items():
            params[INDEX[n]] = v
        prov = proposal_provenance(self.controller, values, {}, {})
        return replace(self.controller, params=params, provenance=prov)

    def _take(self, rows: np.ndarray) -> None:
        """Keep the scans; screen each full segment."""
        if not len(rows) or self.mode == "off":
            self._rows = self._seg_start_ns = None
            return
        buf = rows if self._rows is None else np.concatenate([self._rows, rows])
        stamps = buf["stamp_ns"]
        if self._seg_start_ns is None:
            self._seg_start_ns = int(stamps[0])
        seg_ns = self.segment_ns
        while int(stamps[-1]) - self._seg_start_ns >= seg_ns:
            a, b = self._seg_start_ns, self._seg_start_ns + seg_ns
            i, j = np.searchsorted(stamps, [a, b])
            self._segment(buf[i:j], a, b, buf[:j])
            self._seg_start_ns = b
        keep_ns = self._seg_start_ns - int(FIT_WINDOW_S * 1e9)
        if self._change is not None:
            keep_ns = min(keep_ns, self._change.since_ns)
        self._rows = buf[np.searchsorted(stamps, keep_ns) :].copy()

    def _fit(self, fn, *args, **kw):
        t0 = time.thread_time()
        try:
            return fn(*args, **kw)
        finally:
            self.state.fits += 1
            self.state.fit_cpu_s += time.thread_time() - t0

    def _segment(self, rows: np.ndarray, start_ns: int, end_ns: int, upto: np.ndarray) -> None:
        """One segment of scans ``rows`` [start_ns, end_ns); ``upto``: every scan kept
        up to its end."""
        self._check_pending()
        seg = self._fit(segment_normal, rows, self._reference)
        ch = self._change
        if seg is None:  # too few usable scans: the motion told nothing new
            if ch is not None and ch.stood:
                self._refit(upto, end_ns)
            return
        test = offset_tests(seg, self._base, self._reference, threshold_mm=self.threshold_mm)
        if ch is None:
            if test.moved:
                self._change = _Change(start_ns, seg, end_ns)
            elif self._base.segments < BASELINE_SEGMENTS:
                self._base = self._base + seg
            return
        if not test.moved:
            if ch.stood:
                log.info("upkeep: the change since %s is gone (segment ending %s)",
                         time_or(ch.since_ns), time_or(end_ns))  # fmt: skip
            self._change = None  # a blip, or gone
            self.state.change = ""
            return
        if not ch.stood and self.state.pending is not None:
            self._withdraw(test, start_ns)
        ch.rest = ch.rest + seg
        # the first segment, which the change may have fallen inside of, is left out of
        # the attribution and the refit: a few scans from before it would bias both
        use = offset_tests(ch.rest, self._base, self._reference, threshold_mm=self.threshold_mm)
        ch.names = use.changed
        words = ", ".join(f"{n} {use.shift_mm[OFFSETS.index(n)]:+.2f} mm" for n in use.changed)
        if not ch.names:
            self.state.change = (f"a change since {time_or(ch.since_ns)}, which "
                                 "sensor not yet told apart")  # fmt: skip
            self._maybe_refuse(ch, end_ns, "the motion does not yet tell which sensor moved")
            return
        self.state.change = (f"{words} since {time_or(ch.since_ns)}: "
                             "identifying it from the robot's motion")  # fmt: skip
        self._refit(upto, end_ns)

    def _maybe_refuse(self, ch: _Change, end_ns: int, why: str) -> None:
        if ch.refused or end_ns - ch.since_ns < REFUSE_AFTER_S * 1e9:
            return
        ch.refused = True
        self.state.refused += 1
        self.emit("recalibration_refused", Level.WARNING,
                  f"upkeep: an offset changed since {time_or(ch.since_ns)}, but the robot's "
                  f"motion since does not identify it: {why}; calibrate with loopcal session",
                  names=ch.names, since_ns=ch.since_ns, refusal=why)  # fmt: skip

    def _refit(self, upto: np.ndarray, end_ns: int) -> None:
        ch = self._change
        assert ch is not None
        if not ch.names:
            return
        since = max(ch.first_end_ns, end_ns - int(FIT_WINDOW_S * 1e9))
        rows = upto[np.searchsorted(upto["stamp_ns"], since):]
        fit = self._fit(refit_offsets, rows, self.controller, ch.names, target_mm=self.target_mm)
        if not fit.accepted:
            self._maybe_refuse(ch, end_ns, fit.refusal())
            return
        recent = [n for n in fit.changed
                  if end_ns - self.state.last_proposed_ns.get(n, -(1 << 62)) < self.min_interval_ns]
        if recent:  # fmt: skip
            self.state.change = (f"{', '.join(ch.names)}: identified, held back by the minimum "
                                 f"interval ({', '.join(recent)} changed less than "
                                 f"{self.min_interval_ns / 1e9:g} s ago)")  # fmt: skip
            return
        self._act(fit, ch, int(rows["stamp_ns"][0]), end_ns)

    def _upkeep_table(self, fit: OffsetFit, ch: _Change, since: int, until: int) -> dict:
        base = {n: float(self.controller.params[INDEX[n]]) for n in fit.changed}
        values = fit.values()
        gates = {g.name: bool(g.passed) for g in fit.gates}
        return {
            "mode": self.mode,
            "change_since_ns": int(ch.since_ns), "change_since_utc": time_or(ch.since_ns),
            "window_since_ns": int(since), "window_until_ns": int(until),
            "proposed_ns": time.time_ns(),
            "proposed_utc": now_text(),
            "shift_mm": {n: round(values[n] - base[n], 5) for n in fit.changed},
            "scans": int(fit.scans),
            "target_mm": self.target_mm, "threshold_mm": self.threshold_mm,
            "gates": gates, "recordings": self.directory or "",
        }  # fmt: skip

    def _act(self, fit: OffsetFit, ch: _Change, since: int, until: int) -> None:
        values, std = fit.values(), fit.std()
        table = self._upkeep_table(fit, ch, since, until)
        words = ", ".join(f"{n} {values[n]:.4f} mm ({table['shift_mm'][n]:+.3f} +- {std[n]:.3f})"
                          for n in fit.changed)  # fmt: skip
        details = dict(values={n: round(v, 6) for n, v in values.items()},
                       std={n: round(s, 6) for n, s in std.items()},
                       shift_mm=table["shift_mm"], since_ns=ch.since_ns,
                       window_since_ns=since, window_until_ns=until, scans=table["scans"],
                       gates=table["gates"])  # fmt: skip
        try:
            if self.mode == "report":  # what it would propose (loopcal check), nothing written
                self._reference = self._with(values)
                self._base = Normal()
                self.state.proposals += 1
                self.state.reported.append({"names": list(fit.changed), **details})
                self.emit("recalibration_proposed", Level.WARNING,
                          f"upkeep would propose {words}, changed since "
                          f"{table['change_since_utc']}, every gate passed", path="",
                          **details)  # fmt: skip
            elif self.mode == "propose":
                path = write_proposal(self.controller, values, std, table)
                self.state.pending = read_proposal(self.controller)
                self.state.pending_since_ns = table["proposed_ns"]
                self._reference = self._with(values)
                self._base = Normal()
                self.state.proposals += 1
                self.emit("recalibration_proposed", Level.WARNING,
                          f"upkeep: a recalibration is proposed in {path}: {words}, changed "
                          f"since {table['change_since_utc']}, every gate passed; review it "
                          "(loopcal upkeep status) and apply it (loopcal upkeep apply) or "
                          "discard it", path=str(path), **details)  # fmt: skip
            else:
                params = np.array(self.controller.params, dtype=float)
                for n, v in values.items():
                    params[INDEX[n]] = v
                prov = proposal_provenance(self.controller, values, std, table)
                written = write_back(self.controller, params, prov)
                self.state.written += 1
                self.emit("recalibrated", Level.WARNING,
                          f"upkeep: wrote {words} into {written.path} (changed since "
                          f"{table['change_since_utc']}; every gate passed, as a person's "
                          f"calibration needs; the previous version kept as "
                          f"{written.backup})", path=str(written.path),
                          previous=str(written.backup), **details)  # fmt: skip
        except ControllerConfigError as exc:
            done = "written" if self.mode == "write" else "proposed"
            self.emit("recalibration_refused", Level.ERROR,
                      f"upkeep: {words} identified but not {done}: {exc}",
                      names=fit.changed, since_ns=ch.since_ns, refusal=str(exc))  # fmt: skip
            self._change = None
            return
        for n in fit.changed:
            self.state.last_proposed_ns[n] = until
        self._change = None
        self.state.change = ""

    def _withdraw(self, test: OffsetTests, start_ns: int) -> None:
        """Later scans contradict the pending proposal: take it back."""
        st = self.state
        assert st.pending is not None
        old = st.pending
        try:
            aside = discard_proposal(self.controller)
        except OSError as exc:
            log.error("upkeep: cannot withdraw %s: %s", old.path, exc)
            return
        st.pending, st.withdrawn = None, st.withdrawn + 1
        b = int(np.argmax(test.statistic))
        self.emit("recalibration_withdrawn", Level.WARNING,
                  f"upkeep: the proposal {old.path} is withdrawn (kept as {aside}): the scans "
                  f"since {time_or(start_ns)} disagree with it ({OFFSETS[b]} "
                  f"{test.shift_mm[b]:+.3f} mm from its values)", path=str(old.path),
                  aside=str(aside), names=list(old.values), since_ns=start_ns)  # fmt: skip

    def _check_pending(self) -> None:
        """A pending proposal a person applied or discarded is no longer pending; a
        discarded one's values stay the reference (never two proposals for one change)."""
        st = self.state
        if st.pending is None or self.controller.path is None:
            return
        if not os.path.lexists(proposal_path(self.controller.path)):
            log.info("upkeep: the proposal %s was taken away", st.pending.path)
            st.pending = None

    def _drop(self, why: str) -> None:
        self._change = None
        self.state.change = ""
        log.info("upkeep: the change is gone: %s", why)


def upkeep_mode(mode: str | None, controller: ControllerConfig) -> str:
    """The mode in force: as set, else "propose" with a controller config, "off" without."""
    if mode is not None:
        return mode
    return "off" if controller.path is None else "propose"


def watch_upkeep(recorder: Recorder) -> Upkeep | None:
    """Attach upkeep to a recorder as an observer (``[upkeep].mode``, ``record --upkeep``;
    off without a controller config: it then watches nothing until a reload turns it on);
    returns it."""
    s = recorder.settings
    mode = upkeep_mode(s.upkeep_mode, recorder.controller)
    if mode != "off" and recorder.controller.path is None:
        raise ControllerConfigError(f"[upkeep].mode = {mode!r} needs the robot's "
                                    "controller config ([controller].config)")  # fmt: skip
    up = Upkeep(recorder.controller, recorder.emit, mode=mode, target_mm=s.upkeep_target_mm,
                threshold_mm=s.upkeep_threshold_mm, min_interval_s=s.upkeep_min_interval_s,
                segment_s=s.upkeep_segment_s, directory=s.directory,
                settings=lambda: recorder.settings)  # fmt: skip
    recorder.add_observer(up)
    return up
