"""Upkeep: the daemon keeps the controller config right, from the robot's own motion.

Scans -> segments -> test against the baseline -> change -> told apart -> refit -> gates
-> proposal (or config). The recorder feeds every scan (:meth:`Upkeep.feed`, from the
analysis thread); a worker thread of its own, at the lowest CPU priority, does the rest,
so that neither the recording nor the other observers ever wait for a fit.

1. **Test.** Every ``[upkeep].segment`` of scans (15 s), loop closure on every usable
   scan (moving or still, the channel skew corrected) is summed into the four offsets'
   normal equations at the reference (:mod:`.changes`): the controller config in force,
   with the values of a pending proposal in place of its own (so that a change is
   proposed once). Each segment is tested against the baseline: the reference's own
   calibration (its ``[provenance]`` std), sharpened by the first unchanged segments at
   it. The baseline and any change in progress are kept across restarts
   (:mod:`.upkeep_state`): a change made while the daemon was down is a change against
   it, not a new baseline.
2. **Change.** A segment that moved opens a candidate change; the next segment that tells
   anything either moved too (the change stands, and is said: event ``offset_change``)
   or not (a blip: dropped). The change began within its first segment, which is left out
   of what follows. Which offsets: the smallest explanation of the segments after it that
   beats every other (:func:`.changes.offset_tests`). While the motion cannot tell two
   apart, the change names its candidates, each one's shift, and the move that would tell
   them apart (:func:`~loopcal.daemon.worker.coverage.telling_move`), in the event, the
   status line and the metrics, until it is told or gone. A segment that disagrees with
   every candidate is a further step: the scans from there on alone tell what the config
   needs now.
3. **Refit.** Once told, each new segment refits the named offsets on the scans after the
   change's (latest step's) first segment, at most the latest :data:`FIT_WINDOW_S`, with
   the gates that apply (:func:`~loopcal.daemon.worker.offsets.refit_offsets`). Motion
   that does not make the change identifiable within :data:`REFUSE_AFTER_S` is refused,
   said once (``recalibration_refused``), and the upkeep goes on with the motion that
   comes.
4. **Act.** Accepted: in ``propose`` mode the complete config beside the one in force, in
   ``write`` mode the config itself (:mod:`.upkeep_act`). A sensor that creeps (it moves on
   the same way as its last fix, less than ``min_interval`` ago) is fixed at most every
   ``min_interval``; a swap (either way) is fixed at once. The refit's own scans, moved to
   the new values, are the new baseline: a second change minutes later is told against
   them at once.
5. **Gone.** A change the loops no longer show (the sensor moved back) is dropped, said
   (``offset_change_gone``) if it had been said.
"""

from __future__ import annotations

import logging
import os
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from loopcal.calibration.parameters import INDEX

from ..config.controller import ControllerConfig, ControllerConfigError
from ..defaults import UPKEEP_SEGMENT_S
from ..events import Level
from ..recorder.engine import Recorder
from ..recorder.settings import RecorderSettings
from ..times import time_or
from ..worker.coverage import telling_move
from ..worker.offsets import OFFSETS, calibrated, config_cov, refit_offsets
from ..worker.proposal import Proposal, read_proposal
from .changes import (
    BASELINE_SEGMENTS,
    Normal,
    OffsetTests,
    Reference,
    baseline_of,
    offset_tests,
    segment_normal,
    segments_normal,
)
from .upkeep_act import Acts
from .upkeep_state import Change, Keeper, UpkeepRecord, reference_digest, state_path
from .upkeep_words import Words

log = logging.getLogger(__name__)

MODES = ("off", "propose", "write")
#: the refit uses at most the latest this many seconds of scans since the change
FIT_WINDOW_S = 120.0
#: a standing change the motion has not made identifiable for this long is refused, once
REFUSE_AFTER_S = 600.0
#: a change's scans are linearised again at its best explanation when that moved this far
#: from where they were, mm
RELINEARISE_MM = 0.05
#: the scans since a change kept for that, at most, s
KEEP_S = 1800.0
#: segments tested together too while nothing changed: a shift near the threshold, or a
#: creep, that one segment cannot tell from the noise (a minute of 10-s segments)
WINDOW_SEGMENTS = 6


@dataclass
class UpkeepState:
    """What this run of the upkeep did (the metrics' counters), and what is pending."""

    change: str = ""  # the change in progress in words
    pending: Proposal | None = None
    pending_since_ns: int = 0
    fits: int = 0
    fit_cpu_s: float = 0.0
    proposals: int = 0
    written: int = 0
    withdrawn: int = 0
    refused: int = 0
    #: in report mode, what would have been proposed (the events' details)
    reported: list[dict] = field(default_factory=list)


class Upkeep(Acts, Words):
    """The daemon's upkeep (module docstring), an observer of the recorder's scans.

    Parameters
    ----------
    controller : ControllerConfig
        The config in force.
    emit : callable
        ``emit(kind, level, message, **details)``: the recorder's events.
    mode : {"off", "propose", "write", "report"}
        What an accepted change does; report: nothing written, the proposal only told
        (an event, and ``state.reported``), for ``loopcal check`` on archives.
    target_mm, threshold_mm : float
        The precision a refitted offset must reach, and the smallest shift that counts, mm.
    min_interval_s : float
        The least time between two proposals (or writes) for a creeping offset, s.
    segment_s : float, default 15
        How much of the scans is tested at a time, s of their stamps (``[upkeep].segment``).
    directory : path or None
        The recordings' directory, named in the proposal (for ``loopcal upkeep apply``).
    threaded : bool, default True
        Fit in a worker thread of the lowest priority; False: in :meth:`feed` (offline).
    settings : callable, optional
        The recorder's settings in force: a reload takes ``[upkeep]`` from them again (the
        mode too: off, or on once the reload brings a controller config).
    state : path or None
        Where the baseline and the change in progress are kept across restarts
        (:func:`~.upkeep_state.state_path` of the recordings directory); None: in memory.
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
        state: os.PathLike | None = None,
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
        self.record: UpkeepRecord | None = None
        self.tests: OffsetTests | None = None  # the change's latest attribution
        self.keeper = Keeper(None if state is None else Path(state))
        self.advice = ""  # the move that tells its candidates apart
        self._advised: tuple = ()
        #: why the upkeep must not act now ("" when it may): a technician's session runs
        #: through the daemon, whose own calibration decides (set by ``loopcal daemon``)
        self.hold: Callable[[], str] = lambda: ""
        self._rows: np.ndarray | None = None  # the scans kept: the fit window and a segment
        self._recent: deque = deque(maxlen=WINDOW_SEGMENTS)  # (start, end, Normal)
        self._seg_start_ns: int | None = None
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
        """The config in force changed (a write, an apply, an edit): go on against it."""
        if self._queue is None:
            self._reset(controller)
        else:
            self._queue.put(("reload", controller))

    def close(self, timeout: float = 10.0) -> None:
        """Stop the worker thread (what it was fitting is finished first) and keep the
        record."""
        if self._queue is not None and self._thread is not None:
            self._queue.put(("stop", None))
            self._thread.join(timeout)
        else:
            self._save()

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
                self._save()
                return
            try:
                if what == "reload":
                    self._reset(arg)
                else:
                    self._take(arg)
            except Exception:  # noqa: BLE001 - upkeep fails alone; the recording goes on
                log.exception("upkeep failed on a segment; it goes on from the next one")
                self._rows, self._seg_start_ns = None, None

    def _reset(self, controller: ControllerConfig) -> None:
        """Go on against ``controller`` (and the settings in force): a proposal beside it
        that is still valid stays pending (a restarted daemon does not propose the same
        change again), one that is not is set aside; the record made at the same
        reference is taken up again (a reload, a restart, the upkeep's own write)."""
        if self._settings is not None:
            st = self._settings()
            self.mode = upkeep_mode(st.upkeep_mode, controller)
            self.target_mm, self.threshold_mm = st.upkeep_target_mm, st.upkeep_threshold_mm
            self.min_interval_ns = int(st.upkeep_min_interval_s * 1e9)
            self.segment_ns = int(st.upkeep_segment_s * 1e9)
            self.directory = str(st.directory)
            if self.keeper.path != state_path(st.directory):
                self.keeper, self.record = Keeper(state_path(st.directory)), None
        if self.mode != "off" and controller.path is None:
            log.warning("upkeep off: it needs the robot's controller config")
            self.mode = "off"
        self.controller = controller
        self._recent.clear()
        self.state.change = ""
        self.state.pending = None
        self.reference = controller
        try:
            pending = None if self.mode in ("report", "off") else read_proposal(controller)
        except ControllerConfigError as exc:
            pending = None
            self.set_aside(f"it cannot be applied: {exc}")
        if pending is not None:
            self.state.pending = pending
            since = pending.upkeep.get("proposed_ns")
            self.state.pending_since_ns = since if isinstance(since, int) else time.time_ns()
            self.reference = self.with_values(
                pending.values, pending.std, config_cov(pending.config)
            )
        prev = self.record
        if self.mode != "off":
            digest = reference_digest(self.reference.params)
            self.record = self.keeper.take_up(digest, controller.sha256, prev, self._damaged)
        ch = self.record.change if self.record is not None else None
        self.tests = None
        if ch is not None and ch.stood:
            base = baseline_of(self.record.baseline, self.reference)
            self.tests = offset_tests(ch.rest, base.at(ch.point), threshold_mm=self.threshold_mm)
            self._advise(self.tests)
            if prev is None:  # taken up at start: this run's recording says it too, at once
                ch.announced = False
                self.announce(ch)
        self.vouch()

    def _damaged(self, why: str, where: str) -> None:
        self.emit(
            "upkeep_reset",
            Level.WARNING,
            f"upkeep: its record {self.keeper.path} cannot be taken up ({why}); set aside as "
            f"{where}: the upkeep starts over from the controller config's own calibration",
            path=str(self.keeper.path),
            aside=where,
            error=why,
        )

    def _take(self, rows: np.ndarray) -> None:
        """Keep the scans; test each full segment."""
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
        ch = self.record.change if self.record is not None else None
        if ch is not None:
            keep_ns = min(keep_ns, max(ch.first_end_ns, int(stamps[-1]) - int(KEEP_S * 1e9)))
        self._rows = buf[np.searchsorted(stamps, keep_ns) :].copy()

    def fit(self, fn, *args, **kw):
        t0 = time.thread_time()
        try:
            return fn(*args, **kw)
        finally:
            self.state.fits += 1
            self.state.fit_cpu_s += time.thread_time() - t0

    # ------------------------------------------------------------------ a segment

    def _segment(self, rows: np.ndarray, start_ns: int, end_ns: int, upto: np.ndarray) -> None:
        """One segment of scans ``rows`` [start_ns, end_ns); ``upto``: every scan kept up
        to its end."""
        rec = self.record
        assert rec is not None
        self.check_pending()
        if rec.uncalibrated:
            return
        if rec.watching_since_ns == 0:
            rec.watching_since_ns = start_ns
        seg = self.fit(segment_normal, rows, self.reference)
        dirty = self._step(rec, rows, seg, start_ns, end_ns, upto)
        self._save(end_ns, dirty)
        if rec.change is not None and rec.change.stood:  # said once kept: a kill after
            self.announce(rec.change)  # the words leaves the change in the record

    def _step(
        self,
        rec: UpkeepRecord,
        rows: np.ndarray,
        seg: Normal | None,
        start_ns: int,
        end_ns: int,
        upto: np.ndarray,
    ) -> bool:
        """The segment's part in the change (module docstring); whether ``rec`` changed."""
        ch = rec.change
        if seg is None:  # too few usable scans: the motion told nothing new
            if ch is not None and ch.names:
                self._refit(ch, upto, end_ns)
            return False
        rec.tested += 1
        rec.tested_until_ns = end_ns
        base = baseline_of(rec.baseline, self.reference)
        test = offset_tests(seg, base, threshold_mm=self.threshold_mm)
        # and against the config's own calibration alone: a creep the baseline took in
        # part still shows once the config is off by the threshold
        absolute = offset_tests(
            seg, baseline_of(Normal(), self.reference), threshold_mm=self.threshold_mm
        )
        moved = test.moved or absolute.moved
        if ch is None:
            # the trend: each segment's shift from the config, with its own noise alone
            # (the config's uncertainty is one error common to every segment)
            own = offset_tests(seg, Reference(np.zeros(4), np.zeros((4, 4))), threshold_mm=0)
            return self._watch(rec, seg, start_ns, end_ns, own, moved, base)
        at = (
            seg
            if not ch.point.any()
            else self.fit(segment_normal, rows, self.reference_at(ch.point))
        )
        if at is None:
            return True
        known = self.tests or offset_tests(
            ch.rest if ch.stood else ch.first, base.at(ch.point), threshold_mm=self.threshold_mm
        )
        agrees = self._agrees(at, base.at(ch.point), known)
        if not moved and not agrees:  # the loops close again, and the change is refuted
            self._gone(rec, ch, end_ns)
            return True
        if moved and ch.stood and not agrees:
            ch.first, ch.first_end_ns, ch.steps = seg, end_ns, ch.steps + 1
            ch.rest, ch.point, ch.names = Normal(), np.zeros(4), []
            self.tests = None
            self.state.change = f"it moved on at {time_or(start_ns)}: watching it again"
            return True
        if not ch.stood and self.state.pending is not None:
            self.withdraw(test, start_ns)
        ch.rest = ch.rest + at
        self.tests = use = self._attribute(ch, base, upto, end_ns)
        ch.names = use.changed
        ch.candidates = [c.as_json() for c in use.candidates]
        self._advise(use)
        ch.advice = self.advice
        if not ch.names:
            self.state.change = ""
            self._maybe_refuse(ch, end_ns, f"the motion does not yet tell {use.words()} apart")
            return True
        self.state.change = "identifying it from the robot's motion"
        self._refit(ch, upto, end_ns)
        return True

    def _watch(
        self,
        rec: UpkeepRecord,
        seg: Normal,
        start_ns: int,
        end_ns: int,
        test: OffsetTests,
        moved: bool,
        base: Reference,
    ) -> bool:
        """No change in progress: does this segment, or the latest :data:`WINDOW_SEGMENTS`
        together (a shift near the threshold, or a creep, that one segment cannot tell
        from the noise), open one? Else the segment joins a baseline not yet full.
        ``test``: the segment's shifts from the config, its own noise alone, which the
        trend keeps (a creep shows there however much of it the baseline took in)."""
        recent = self._recent
        recent.append((start_ns, end_ns, seg))
        if moved and rec.tested == 1 and not calibrated(self.reference):
            rec.uncalibrated = True  # health says it, once: nothing to keep up
            log.warning(
                "upkeep: the loops do not close at %s, which loopcal never "
                "calibrated: nothing to keep up until it is calibrated",
                self.controller.path,
            )
            return True
        if moved:
            rec.change = Change(start_ns, seg, end_ns)
            recent.clear()
            return True
        if len(recent) == WINDOW_SEGMENTS:
            win = sum((n for _, _, n in list(recent)[1:]), Normal())
            # a creep that stopped may have left a shift under the threshold: a quarter
            # of it counts then, once (later fixes of an offset alike would take it in)
            least = self.threshold_mm / 4 if rec.settle else self.threshold_mm
            rec.settle = []
            if any(
                offset_tests(win, ref, threshold_mm=least).moved
                for ref in (base, baseline_of(Normal(), self.reference))
            ):
                a, b, first = recent[0]
                # stands (its segments agree); gradual: no one segment could tell it
                rec.change = Change(a, first, b, rest=win, gradual=True)
                recent.clear()
                return True
        rec.note_trend(end_ns, test.shift_mm, test.std_mm)  # nothing moved: a creep's ramp
        self.warn_creep(rec)
        if rec.baseline.segments < BASELINE_SEGMENTS:
            rec.baseline = rec.baseline + seg
        return True

    def reference_at(self, point: np.ndarray) -> ControllerConfig:
        """The reference with its offsets moved by ``point`` (4,) mm."""
        params = np.array(self.reference.params, dtype=float)
        for i, n in enumerate(OFFSETS):
            params[INDEX[n]] += point[i]
        return replace(self.reference, params=params)

    def _attribute(self, ch: Change, base: Reference, upto: np.ndarray, end_ns: int) -> OffsetTests:
        """The change's explanations, its scans linearised again at the best one when it
        moved :data:`RELINEARISE_MM` from where they were (:mod:`.changes`), if the scans
        since the change are all still kept (not after a restart)."""
        use = offset_tests(ch.rest, base.at(ch.point), threshold_mm=self.threshold_mm)
        best = use.best
        stamps = upto["stamp_ns"]
        if best is None or not len(stamps) or int(stamps[0]) > ch.first_end_ns:
            return use
        point = best.delta()[0]
        if np.abs(point - ch.point).max() < RELINEARISE_MM:
            return use
        edges = np.arange(ch.first_end_ns, end_ns + 1, self.segment_ns)
        rest = self.fit(segments_normal, upto, self.reference_at(point), edges)
        if not rest.segments:
            return use
        ch.rest, ch.point = rest, point
        return offset_tests(rest, base.at(point), threshold_mm=self.threshold_mm)

    def _agrees(self, seg: Normal, base: Reference, known: OffsetTests) -> bool:
        """Whether a segment agrees with an explanation of the change not ruled out."""
        for c in known.candidates:
            against = base.moved_by(*c.delta())
            if not offset_tests(seg, against, threshold_mm=self.threshold_mm).moved:
                return True
        return False

    def _advise(self, tests: OffsetTests) -> None:
        """The move that tells the candidates apart (made again only when they change)."""
        key = tuple(c.names for c in tests.candidates)
        if len(tests.candidates) < 2:
            self.advice, self._advised = "", ()
        elif key != self._advised:
            shifts = [c.delta()[0] for c in tests.candidates]
            self.advice = telling_move(np.asarray(self.reference.params), shifts).text
            self._advised = key

    def _gone(self, rec: UpkeepRecord, ch: Change, end_ns: int) -> None:
        rec.change, self.tests, self.advice, self.state.change = None, None, "", ""
        if ch.announced:
            self.emit(
                "offset_change_gone",
                Level.INFO,
                f"upkeep: the loops close again at the controller config (the change "
                f"since {time_or(ch.since_ns)} is gone: the sensor moved back, or it "
                "was no change of an offset)",
                since_ns=ch.since_ns,
                until_ns=end_ns,
            )
        elif ch.stood:
            log.info("upkeep: the change since %s is gone", time_or(ch.since_ns))

    def _maybe_refuse(self, ch: Change, end_ns: int, why: str) -> None:
        if ch.refused or end_ns - ch.since_ns < REFUSE_AFTER_S * 1e9:
            return
        ch.refused = True
        self.refuse(
            ch,
            end_ns,
            why,
            Level.WARNING,
            f"upkeep: an offset changed since {time_or(ch.since_ns)}, but the robot's "
            f"motion since does not identify it: {why}; it goes on watching, and "
            "fixes it as soon as the motion tells (or calibrate with loopcal "
            "session)",
        )

    def _refit(self, ch: Change, upto: np.ndarray, end_ns: int) -> None:
        since = max(ch.first_end_ns, end_ns - int(FIT_WINDOW_S * 1e9))
        rows = upto[np.searchsorted(upto["stamp_ns"], since) :]
        fit = self.fit(refit_offsets, rows, self.controller, ch.names, target_mm=self.target_mm)
        if not fit.accepted:
            self._maybe_refuse(ch, end_ns, fit.refusal())
            return
        if why := self.hold():
            self.state.change = f"identified; held while {why}"
            return
        values = fit.values()
        creeping = [
            n
            for n in fit.changed
            if self.creeping(n, values[n] - float(self.controller.params[INDEX[n]]), ch, end_ns)
        ]
        if creeping and len(creeping) == len(fit.changed):  # a creep alone waits
            self.state.change = (
                f"identified; a creep, held back by the minimum interval "
                f"({', '.join(creeping)} changed less than "
                f"{self.min_interval_ns / 1e9:g} s ago and is still moving)"
            )
            return
        self.act(fit, ch, int(rows["stamp_ns"][0]), end_ns)

    def _save(self, now_ns: int | None = None, dirty: bool = True) -> None:
        """Keep the record (:mod:`.upkeep_state`) if it changed, or a minute went by."""
        if self.record is not None and self.mode not in ("off", "report"):
            self.keeper.save(self.record, now_ns, dirty)


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
    up = Upkeep(
        recorder.controller,
        recorder.emit,
        mode=mode,
        target_mm=s.upkeep_target_mm,
        threshold_mm=s.upkeep_threshold_mm,
        min_interval_s=s.upkeep_min_interval_s,
        segment_s=s.upkeep_segment_s,
        directory=s.directory,
        settings=lambda: recorder.settings,
        state=state_path(s.directory),
    )
    recorder.add_observer(up)
    return up
