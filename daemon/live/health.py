"""Loop-closure health: the daemon watches whether the loops still close at the controller
config in force, and names the sensor whose offset moved.

Scans -> still poses -> loop closure -> drift test -> events. The recorder feeds every scan
it receives (:meth:`HealthMonitor.feed`); still poses are found as the worker finds them
(:func:`loopcal.daemon.worker.recorded_poses.poses_of_scans`), each as soon as the plate moves on,
and each
new pose runs the likelihood-ratio test of :mod:`loopcal.calibration.closure` over the last 30
poses: "sensor i's offset moved, and the latest k poses show it", for each sensor and every k (as a
step, and as a creep growing over those poses), against the noise of the poses' own
readings and the uncertainty of the config's calibration.

An alarm (event ``offset_drift``, a warning in the log and the MCAP events, and the systemd
STATUS line) needs the best sensor's statistic above the threshold that gives a
false-alarm probability of ``false_alarm`` per pose when nothing moved (Bonferroni over the
four sensors and the change points), the best change point to leave at least
:data:`MIN_AFFECTED` poses shifted (fewer do not tell the sensors apart), and the pattern to
point clearly at that sensor (its statistic at least :data:`ATTRIBUTION_MARGIN` above the
runner-up's, and the same sensor when a creep is tested too). It is raised again if the
estimated shift grows by :data:`REPORT_STEP_MM` (a creep; at most every
:data:`REPORT_EVERY_S` of recording), and cleared (event ``offset_drift_cleared``) once that
sensor's statistic falls below :data:`CLEAR_STATISTIC`.

Two cases are not a drift, and are not told as one:

- **No controller config.** The daemon without one records at the reference geometry,
  which no real robot matches: its loops never close there, and nothing moved. Health then
  watches nothing, and its status line says it needs the robot's config
  (``require_config``, as the recorder runs it).
- **Loops that never closed.** When the poses already disagree with the config from the
  first one the monitor saw (a sensor replaced before the daemon started, a config never
  calibrated), no offset moved during the recording: the event is ``loops_open`` ("the
  loops do not close at the controller config since the recording began: calibrate"),
  once, and no ``offset_drift`` is raised while it stands (every later window disagrees
  too, and would name whichever sensor fits best). A reload starts over.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from loopcal.calibration.closure import (
    Closure,
    DriftTest,
    PoseModels,
    drift_test,
    loop_closure,
    pose_models,
    step_tests,
    threshold,
)
from loopcal.calibration.parameters import INDEX, SL_OFFSET
from loopcal.calibration.poses import pose_noise_volts

from ..config.controller import ControllerConfig
from ..events import Level
from ..recorder.engine import Recorder
from ..recorder.settings import DEFAULTS
from ..worker.coverage import telling_move
from ..worker.recorded_poses import RecordedPoses, completed_poses, margin_scans, window_scans

WINDOW = 30  # poses per test
MIN_AFFECTED = 6  # a shift must show in at least this many of the latest poses
CHANGE_POINTS = WINDOW
ATTRIBUTION_MARGIN = threshold(1e-6, tests=1)  # 23.9: the sensor is 1.5e5x likelier
CLEAR_STATISTIC = threshold(1e-2, tests=CHANGE_POINTS)  # 12.9
REPORT_STEP_MM = 0.5
#: a disagreement that reaches back into the first poses seen is no drift: the loops never
#: closed (a change within them is told the same way: "since the recording began")
EARLY_POSES = 3
REPORT_EVERY_S = 60.0  # a growing shift of the same sensor is reported at most this often
#: the offsets' standard deviation assumed for a config without a calibration's provenance
DEFAULT_CONFIG_STD_MM = 0.05
#: probability per still pose of an alarm when nothing moved: the daemon's [health].false_alarm
FALSE_ALARM: float = DEFAULTS["health_false_alarm"]

log = logging.getLogger(__name__)

_BATCH = 512  # windows tested at once (memory: about 30 kB each)

Emit = Callable[..., None]  # (kind, level, message, **details)


@dataclass(frozen=True)
class _Poses:
    """Still poses in order: mean volts (n, 4), one scan's noise (n, 4), scans averaged
    (n,), stamps (n,) ns, and the config's :class:`PoseModels` of them."""

    volts: np.ndarray
    noise: np.ndarray
    counts: np.ndarray
    stamps: np.ndarray
    models: PoseModels

    def __len__(self) -> int:
        return len(self.volts)

    def __getitem__(self, k: slice) -> _Poses:
        return _Poses(self.volts[k], self.noise[k], self.counts[k], self.stamps[k], self.models[k])

    def join(self, other: _Poses) -> _Poses:
        return _Poses(*(np.concatenate([a, b]) for a, b in zip(
            (self.volts, self.noise, self.counts, self.stamps),
            (other.volts, other.noise, other.counts, other.stamps), strict=True)),
            PoseModels.stack([self.models, other.models]))  # fmt: skip


@dataclass
class HealthState:
    """What the status line shows: poses checked, the latest test, the active alarm, and
    whether the loops have not closed since the first pose (``open_since_start``)."""

    poses: int = 0
    last: DriftTest | None = None
    alarm_sensor: int | None = None
    alarm_shift_mm: float = 0.0
    alarm_stamp_ns: int = 0
    open_since_start: bool = False
    #: the stamps of the first :data:`EARLY_POSES` poses since the (re)start, ns
    early_ns: tuple[int, ...] = ()
    #: the sensors that may have moved while the poses cannot tell which (an
    #: ``offset_drift_unattributed`` stands), likeliest first; empty otherwise
    unattributed: tuple[int, ...] = ()
    #: and each one's shift, mm
    unattributed_mm: tuple[float, ...] = ()


def config_covariance(controller: ControllerConfig) -> np.ndarray:
    """(20, 20) covariance of the config's parameters: the standard deviations its
    ``[provenance]`` records (a loopcal calibration), else :data:`DEFAULT_CONFIG_STD_MM` on
    the four offsets."""
    C = np.zeros((20, 20))
    std = (controller.provenance or {}).get("std") or {}
    if isinstance(std, dict) and std:
        for name, s in std.items():
            if name in INDEX and isinstance(s, (int, float)) and np.isfinite(s):
                C[INDEX[name], INDEX[name]] = float(s) ** 2
    else:
        for i in range(SL_OFFSET.start, SL_OFFSET.stop):
            C[i, i] = DEFAULT_CONFIG_STD_MM**2
    return C


class HealthMonitor:
    """Watches loop closure over the scans fed to it; calls ``emit`` for events.

    controller: the config in force. false_alarm: probability per pose of an alarm when
    nothing moved. on_test: called with the newest pose's stamp (ns) and the test's result
    after every test (``loopcal check`` draws them; the metrics export them).
    require_config: watch nothing while the config is the reference geometry (no file:
    ``controller.path`` None), as the recorder runs it.
    """

    name = "loop-closure health"

    def __init__(
        self,
        controller: ControllerConfig,
        emit: Emit,
        *,
        false_alarm: float = FALSE_ALARM,
        on_test: Callable[[int, DriftTest], None] | None = None,
        require_config: bool = False,
    ) -> None:
        self.emit = emit
        self.require_config = require_config
        self.on_test = on_test
        self.false_alarm = false_alarm
        self.threshold = threshold(false_alarm, tests=4 * CHANGE_POINTS)
        self._buf: np.ndarray | None = None
        self._last_key: tuple[int, int] = (-1, -1)  # (epoch, counter) of the last pose's end
        self.reload(controller)

    def reload(self, controller: ControllerConfig) -> None:
        """Start over at a new controller config (a reload): earlier poses no longer count."""
        self.params = np.array(controller.params, dtype=float)
        self.covariance = config_covariance(controller)
        prov = controller.provenance or {}
        #: when loopcal calibrated the config (its provenance), None if it never did
        self.calibrated_utc = (
            str(prov.get("written_utc", "?"))
            if isinstance(prov.get("std"), dict) and prov["std"]
            else None
        )
        #: False while there is no controller config to check the loops against
        self.watching = not (self.require_config and controller.path is None)
        # the last WINDOW poses' mean volts (4,), scan noise (4,), scans averaged, stamp ns,
        # and what the config predicts for them (PoseModels)
        self._window: _Poses | None = None
        self.state = HealthState()

    # ------------------------------------------------------------------ input

    def feed(self, rows: np.ndarray, *, final: bool = False) -> None:
        """New scans (SCAN_DTYPE rows, in order); tests every still pose they complete.
        final: no scan will follow (the end of a recording read offline): a pose the plate
        was still held in at the end counts too, as ``loopcal info`` counts it."""
        if (len(rows) == 0 and not final) or not self.watching:
            return
        buf = rows if self._buf is None else np.concatenate([self._buf, rows])
        if not len(buf):
            return
        P, done, keep_from = completed_poses(buf, final=final)
        new = []  # the poses this feed completes (the plate has moved on from them)
        for k in done:
            a, b = P.rows[k]
            key = (int(buf["epoch"][a]), int(buf["counter64"][a]))
            if key <= self._last_key:
                continue
            self._last_key = (int(buf["epoch"][b - 1]), int(buf["counter64"][b - 1]))
            new.append(k)
        if new:
            self._add(_Poses(P.volts[new], P.scan_noise[new], P.counts[new].astype(float),
                             P.stamp_ns[new].astype(np.int64),
                             pose_models(P.volts[new], self.params)))  # fmt: skip
        if not final:
            keep_from = self._settle(buf, P, len(done) < len(P), keep_from)
        self._buf = buf[keep_from:].copy()

    def _settle(self, buf: np.ndarray, P: RecordedPoses, open_pose: bool, keep_from: int) -> int:
        """Where to keep ``buf`` from for the next search, so that a feed searches its new
        scans and a bounded context, not every scan since the last pose (up to
        :data:`~loopcal.daemon.worker.recorded_poses.POSE_BUFFER_S` while the plate moves).

        A row the plate was not still at, whose every still window is in ``buf`` (settled),
        is in no later pose: the open pose begins after it (the row before the open pose),
        or, with none, every settled row after the kept ones is such a row (a still one would
        be in a pose of ``buf``); take the last one, r. The rows from r on are still or not
        in a search of ``buf[s:]`` exactly as in one of ``buf``, for s = r + 1 - window -
        margin (a gap's margin before them, and their windows, are in it), so the poses a
        later search finds after r are the same; those it finds up to r (rows whose context
        was cut) are not poses, and are skipped as counted ones are (``_last_key``)."""
        rate = P.scan_rate_hz  # the window and the margin as poses_of_scans derives them
        window, margin = window_scans(rate), margin_scans(rate)
        if open_pose:
            r = int(P.rows[-1][0]) - 1  # the row before it: it begins no split piece here
            if r < keep_from:
                return keep_from  # the open pose goes on from the kept rows' start
        else:
            r = len(buf) - window  # the last settled row
            if r < keep_from + window:  # the kept rows may begin with a still one
                return keep_from
        s = r + 1 - window - margin
        if s <= keep_from:
            return keep_from
        self._last_key = max(self._last_key, (int(buf["epoch"][r]), int(buf["counter64"][r])))
        return s

    # ------------------------------------------------------------------ the test

    def _add(self, fresh: _Poses) -> None:
        """Append a feed's new poses and test the window each of them completes: the last
        :data:`WINDOW` poses, from :data:`MIN_AFFECTED` on. The windows' tests run together
        (:func:`loopcal.calibration.closure.step_tests`); what they mean is judged in order."""
        old = 0 if self._window is None else len(self._window)
        poses = fresh if self._window is None else self._window.join(fresh)
        if len(self.state.early_ns) < EARLY_POSES:
            early = self.state.early_ns + tuple(int(t) for t in fresh.stamps)
            self.state.early_ns = early[:EARLY_POSES]
        ends = np.arange(old, len(poses)) + 1  # each new pose closes the window ending at it
        self.state.poses += len(fresh)
        ends = ends[ends >= MIN_AFFECTED]
        starts = np.maximum(ends - WINDOW, 0)
        for m in np.unique(ends - starts):  # WINDOW, but fewer poses after a (re)start
            sel = ends[ends - starts == m]
            for lo in range(0, len(sel), _BATCH):
                self._test(poses, sel[lo : lo + _BATCH] - m, int(m))
        self._window = poses[max(0, len(poses) - WINDOW) :]

    def _test(self, poses: _Poses, starts: np.ndarray, m: int) -> None:
        """Test the windows of m poses beginning at ``starts``, then judge them in order."""
        win = starts[:, None] + np.arange(m)  # (B, m) pose indices
        # one scan's noise per channel, pooled over each window (a pose's own estimate from
        # a second of scans scatters by 15 %); the converter's rounding does not average out
        scan = np.sqrt(np.mean(np.square(poses.noise[win]), axis=1))  # (B, 4)
        sigma = pose_noise_volts(np.repeat(scan, m, axis=0), poses.counts[win].ravel())
        flat = win.ravel()
        c = loop_closure(poses.volts[flat], self.params, sigma, models=poses.models[flat])
        shape = win.shape
        closures = (c.error.reshape(shape), c.offset_pattern.reshape(shape + (4,)),
                    c.information.reshape(shape + (-1,)), c.usable.reshape(shape))  # fmt: skip
        tests = step_tests(*closures, self.covariance)
        for b, best in enumerate(tests):
            self._judge(best, poses.stamps[win[b]], lambda b=b: Closure(*(x[b] for x in closures)))

    def _judge(self, best: DriftTest, stamps: np.ndarray, closure: Callable[[], Closure]) -> None:
        """What a window's test means: an alarm, a growing shift, a clear, or nothing."""
        self.state.last = best
        if self.on_test is not None:
            self.on_test(int(stamps[-1]), best)
        st = self.state
        if st.unattributed and float(np.max(best.statistic)) < CLEAR_STATISTIC:
            self.emit(
                "offset_drift_cleared",
                Level.INFO,
                f"the loops close again at the controller config (over the last {best.poses} "
                "poses): the offset that moved is back",
                sensor=None,
                poses=best.poses,
            )
            st.unattributed, st.unattributed_mm = (), ()
        if st.alarm_sensor is not None:
            if best.statistic[st.alarm_sensor - 1] < CLEAR_STATISTIC:
                self.emit(
                    "offset_drift_cleared", Level.INFO,
                    f"sensor {st.alarm_sensor}'s loops close again at the controller config "
                    f"(over the last {best.poses} poses)",
                    sensor=st.alarm_sensor, poses=best.poses,
                )  # fmt: skip
                st.alarm_sensor = None
                return
        T = float(np.max(best.statistic))
        if st.open_since_start:
            return  # told once; every later window disagrees too
        if T >= self.threshold and int(stamps[-best.affected]) <= st.early_ns[-1]:
            self._open_since_start(best, int(stamps[-1]), T)
            return
        if T < self.threshold or best.affected < MIN_AFFECTED:
            return
        if best.margin < ATTRIBUTION_MARGIN:
            self._unattributed(best, stamps)
            return
        # a creep fits a step of the wrong sensor now and then, and a step a creep: both
        # shapes must name the same sensor
        shaped = drift_test(closure(), self.covariance, change_points=True, creep=True)
        if shaped.sensor != best.sensor:
            self._unattributed(best, stamps)
            return
        st.unattributed, st.unattributed_mm = (), ()
        if shaped.shape == "creep":  # still moving: the creep's estimate is its shift now
            best = shaped
        sensor = best.sensor
        shift = float(best.shift_mm[sensor - 1])
        now = int(stamps[-1])
        if st.alarm_sensor == sensor and (
            abs(shift - st.alarm_shift_mm) < REPORT_STEP_MM
            or np.sign(shift) != np.sign(st.alarm_shift_mm)  # on its way back: see the clear
            or now - st.alarm_stamp_ns < REPORT_EVERY_S * 1e9
        ):
            return
        st.alarm_sensor, st.alarm_shift_mm, st.alarm_stamp_ns = sensor, shift, now
        std = float(best.std_mm[sensor - 1])
        self.emit(
            "offset_drift", Level.WARNING,
            f"offset drift: sensor {sensor}'s offset has moved by {shift:+.2f} mm "
            f"(+-{std:.2f}){' and is still moving' if best.shape == 'creep' else ''} against "
            "the controller config; check that LVDT's mounting and recalibrate "
            "(loopcal calibrate)",
            sensor=sensor, shift_mm=round(shift, 4), std_mm=round(std, 4),
            since_ns=int(stamps[-best.affected]),
            statistic=round(T, 2), threshold=round(self.threshold, 2),
            margin=round(best.margin, 2), poses=best.affected, shape=best.shape,
            false_alarm=self.false_alarm,
        )  # fmt: skip

    def _unattributed(self, best: DriftTest, stamps: np.ndarray) -> None:
        """The loops no longer close, and the poses cannot tell which sensor moved: said
        once, naming the candidates (until the loops close again, or an alarm names one)."""
        st = self.state
        if st.alarm_sensor is not None or st.unattributed:
            return
        T = float(np.max(best.statistic))
        cands = [
            i for i in np.argsort(-best.statistic) if best.statistic[i] > T - ATTRIBUTION_MARGIN
        ]
        st.unattributed = tuple(int(i) + 1 for i in cands)
        st.unattributed_mm = tuple(round(float(best.shift_mm[i]), 4) for i in cands)
        words = " or ".join(f"sensor {i + 1} ({best.shift_mm[i]:+.2f} mm)" for i in cands)
        shifts = [np.eye(4)[i] * best.shift_mm[i] for i in cands]
        move = telling_move(self.params, shifts, still=True).text if len(cands) > 1 else ""
        self.emit(
            "offset_drift_unattributed",
            Level.WARNING,
            f"the loops no longer close at the controller config: the offset of {words} "
            f"moved, and the poses so far cannot tell which; check those LVDTs' mountings"
            + (f"; to tell them apart, {move}" if move else ""),
            candidates=[
                {
                    "sensor": int(i) + 1,
                    "shift_mm": round(float(best.shift_mm[i]), 4),
                    "std_mm": round(float(best.std_mm[i]), 4),
                }
                for i in cands
            ],
            since_ns=int(stamps[-best.affected]),
            statistic=round(T, 2),
            threshold=round(self.threshold, 2),
            margin=round(best.margin, 2),
            poses=best.affected,
            advice=move,
            false_alarm=self.false_alarm,
        )

    def _open_since_start(self, best: DriftTest, now: int, statistic: float) -> None:
        """The poses disagree with the config from the first one on: not a drift during the
        recording. At a config loopcal calibrated, something changed since that
        calibration (a sensor swapped while the daemon was down); at one it never
        calibrated, the config does not describe this robot."""
        st = self.state
        st.open_since_start = True
        sensor = best.sensor
        T = float(np.max(best.statistic))
        cands = [
            i for i in np.argsort(-best.statistic) if best.statistic[i] > T - ATTRIBUTION_MARGIN
        ]
        words = " or ".join(f"sensor {i + 1}'s offset {best.shift_mm[i]:+.2f} mm" for i in cands)
        if self.calibrated_utc is not None:
            why = (
                f"something changed since its calibration ({self.calibrated_utc}): "
                f"{words}; the upkeep identifies it from the robot's motion, or calibrate "
                "with loopcal session"
            )
        else:
            why = (
                "the config, which loopcal never calibrated, does not describe this robot: "
                "calibrate with loopcal session"
            )
        self.emit(
            "loops_open",
            Level.WARNING,
            "the loops do not close at the controller config since the recording began "
            f"(all {best.affected} poses so far disagree with it): {why}",
            poses=best.affected,
            since_ns=st.early_ns[0],
            detected_ns=now,
            statistic=round(statistic, 2),
            threshold=round(self.threshold, 2),
            largest_sensor=sensor,
            largest_shift_mm=round(float(best.shift_mm[sensor - 1]), 4),
            calibrated_utc=self.calibrated_utc,
            candidates=[
                {"sensor": int(i) + 1, "shift_mm": round(float(best.shift_mm[i]), 4)} for i in cands
            ],
            false_alarm=self.false_alarm,
        )

    # ------------------------------------------------------------------ output

    def metrics(self) -> list:
        """Prometheus metric families (:mod:`loopcal.daemon.recorder.metrics`): per sensor the
        latest test's statistic, estimated offset shift and its standard deviation, and
        whether an alarm stands; the threshold; the poses checked."""
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        st = self.state
        out = [
            CounterMetricFamily(
                "loopcal_loop_closure_poses", "still poses checked for loop closure", value=st.poses
            ),  # fmt: skip
            GaugeMetricFamily(
                "loopcal_loop_closure_threshold",
                "the statistic an alarm needs",
                value=self.threshold,
            ),  # fmt: skip
        ]
        per_sensor = [
            ("loopcal_loop_closure_statistic", "the latest test's statistic (chi-square, 1 "
             "dof when nothing moved)", "statistic"),
            ("loopcal_offset_shift_mm", "the latest test's estimated shift of the sensor's "
             "offset, mm", "shift_mm"),
            ("loopcal_offset_shift_std_mm", "the standard deviation of that estimate, mm",
             "std_mm"),
        ]  # fmt: skip
        for name, doc, attr in per_sensor:
            fam = GaugeMetricFamily(name, doc, labels=["sensor"])
            if st.last is not None:
                for i, v in enumerate(getattr(st.last, attr)):
                    fam.add_metric([str(i + 1)], float(v))
            out.append(fam)
        out.append(
            GaugeMetricFamily(
                "loopcal_loops_open",
                "1 while the loops do not close at the controller config "
                "(an offset_drift alarm, one the poses cannot attribute yet, or loops_open)",
                value=1.0
                if (st.alarm_sensor is not None or st.unattributed or st.open_since_start)
                else 0.0,
            )
        )
        alarm = GaugeMetricFamily("loopcal_offset_drift_alarm", "1 while an offset_drift alarm "
                                  "stands for the sensor", labels=["sensor"])  # fmt: skip
        for i in range(4):
            alarm.add_metric([str(i + 1)], 1.0 if st.alarm_sensor == i + 1 else 0.0)
        out.append(alarm)
        return out

    def status(self) -> str:
        """A few words for the STATUS line."""
        st = self.state
        if not self.watching:
            return ("loop closure not watched: it needs the robot's controller config "
                    "(--controller-config, [controller].config)")  # fmt: skip
        if st.open_since_start:
            if self.calibrated_utc is not None:
                return (
                    "LOOPS DO NOT CLOSE at the controller config since the start: changed "
                    f"since its calibration ({self.calibrated_utc})"
                )
            return (
                "LOOPS DO NOT CLOSE at the controller config since the start: calibrate "
                "(loopcal session)"
            )
        if st.alarm_sensor is not None:
            return f"OFFSET DRIFT sensor {st.alarm_sensor} {st.alarm_shift_mm:+.2f} mm"
        if st.unattributed:
            words = " or ".join(
                f"sensor {s} {mm:+.2f} mm"
                for s, mm in zip(st.unattributed, st.unattributed_mm, strict=True)
            )
            return f"LOOPS OPEN: {words}, not told apart yet"
        if st.last is None:
            return f"loop closure: {st.poses} still poses (need {MIN_AFFECTED})"
        worst = int(np.argmax(np.abs(st.last.shift_mm)))
        return (
            f"loops close ({st.last.poses} poses; largest offset change sensor {worst + 1} "
            f"{st.last.shift_mm[worst]:+.2f} +- {st.last.std_mm[worst]:.2f} mm)"
        )


def watch_health(recorder: Recorder) -> HealthMonitor | None:
    """Attach loop-closure health to a recorder as an observer, unless its settings switch
    it off (``[health].enabled``, ``record --no-health``); returns the monitor."""
    s = recorder.settings
    if not s.health:
        return None
    monitor = HealthMonitor(recorder.controller, recorder.emit, false_alarm=s.health_false_alarm,
                            require_config=True)  # fmt: skip
    if not monitor.watching:
        log.warning("loop-closure health watches nothing: it needs the robot's controller "
                    "config (--controller-config, [controller].config); at the reference "
                    "geometry the loops of a real robot never close")  # fmt: skip
    recorder.add_observer(monitor)
    return monitor
