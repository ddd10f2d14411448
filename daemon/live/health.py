"""Loop-closure health: the daemon watches whether the loops still close at the controller
config in force, and names the sensor whose offset moved.

Scans -> still poses -> loop closure -> drift test -> events. The recorder feeds every scan
it receives (:meth:`HealthMonitor.feed`); still poses are found as the worker finds them
(:func:`daemon.worker.poses.poses_of_scans`), each as soon as the plate moves on, and each new pose
runs the likelihood-ratio test of :mod:`calibration.closure` over the last 30 poses:
"sensor i's offset moved, and the latest k poses show it", for each sensor and every k (as a
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
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtri

from calibration.closure import (
    DriftTest,
    PoseModels,
    drift_test,
    loop_closure,
    pose_models,
    threshold,
)
from calibration.parameters import INDEX, SL_OFFSET
from calibration.poses import pose_noise_volts

from ..config.controller import ControllerConfig
from ..events import Level
from ..recorder.engine import Recorder
from ..worker.poses import LONGEST_POSE_S, poses_of_scans

WINDOW = 30  # poses per test
MIN_AFFECTED = 6  # a shift must show in at least this many of the latest poses
CHANGE_POINTS = WINDOW
ATTRIBUTION_MARGIN = float(chdtri(1, 1e-6))  # 23.9: the sensor is 1.5e5x likelier
CLEAR_STATISTIC = float(chdtri(1, 1e-2 / CHANGE_POINTS))  # 12.1
REPORT_STEP_MM = 0.5
REPORT_EVERY_S = 60.0  # a growing shift of the same sensor is reported at most this often
#: the offsets' standard deviation assumed for a config without a calibration's provenance
DEFAULT_CONFIG_STD_MM = 0.05
FALSE_ALARM = 1e-8
BUFFER_S = 3 * LONGEST_POSE_S  # scans kept while no pose is found (the plate moving)

Emit = Callable[..., None]  # (kind, level, message, **details)


@dataclass
class HealthState:
    """What the status line shows: poses checked, the latest test, the active alarm."""

    poses: int = 0
    last: DriftTest | None = None
    alarm_sensor: int | None = None
    alarm_shift_mm: float = 0.0
    alarm_stamp_ns: int = 0


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
    """

    name = "loop-closure health"

    def __init__(
        self,
        controller: ControllerConfig,
        emit: Emit,
        *,
        false_alarm: float = FALSE_ALARM,
        on_test: Callable[[int, DriftTest], None] | None = None,
    ) -> None:
        self.emit = emit
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
        # the last WINDOW poses: (mean volts (4,), scan noise (4,), scans averaged, stamp ns,
        # what the config predicts for it: PoseModels of one pose)
        self._poses: deque[tuple] = deque(maxlen=WINDOW)
        self.state = HealthState()

    # ------------------------------------------------------------------ input

    def feed(self, rows: np.ndarray) -> None:
        """New scans (SCAN_DTYPE rows, in order); tests every still pose they complete."""
        if len(rows) == 0:
            return
        buf = rows if self._buf is None else np.concatenate([self._buf, rows])
        P = poses_of_scans(buf)
        keep_from = 0
        new = []  # the poses this feed completes (the plate has moved on from them)
        for k in range(len(P)):
            a, b = P.rows[k]
            if b >= len(buf):  # still growing: the plate has not moved on yet
                break
            key = (int(buf["epoch"][a]), int(buf["counter64"][a]))
            if key <= self._last_key:
                continue
            self._last_key = (int(buf["epoch"][b - 1]), int(buf["counter64"][b - 1]))
            keep_from = b
            new.append(k)
        # what the config predicts for each pose, once (all of this feed's at once)
        models = pose_models(P.volts[new], self.params) if new else None
        for j, k in enumerate(new):
            self._poses.append((P.volts[k], P.scan_noise[k], int(P.counts[k]),
                                int(P.stamp_ns[k]), models[j]))  # fmt: skip
            self.state.poses += 1
            if len(self._poses) >= MIN_AFFECTED:
                self._test()
        rate = P.scan_rate_hz
        keep_from = max(keep_from, len(buf) - int(BUFFER_S * rate))
        self._buf = buf[keep_from:].copy()

    # ------------------------------------------------------------------ the test

    def _test(self) -> None:
        volts, noise, counts, stamps, models = zip(*self._poses, strict=True)
        V = np.array(volts)
        counts = np.array(counts, dtype=float)
        # one scan's noise per channel, pooled over the window (a pose's own estimate from
        # a second of scans scatters by 15 %); the converter's rounding does not average out
        scan = np.sqrt(np.mean(np.square(noise), axis=0))
        sigma = pose_noise_volts(scan, counts)
        closure = loop_closure(V, self.params, sigma, models=PoseModels.stack(list(models)))
        best = drift_test(closure, self.covariance, change_points=True)
        self.state.last = best
        if self.on_test is not None:
            self.on_test(stamps[-1], best)
        st = self.state
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
        if T < self.threshold or best.affected < MIN_AFFECTED or best.margin < ATTRIBUTION_MARGIN:
            return
        # a creep fits a step of the wrong sensor now and then, and a step a creep: both
        # shapes must name the same sensor
        shaped = drift_test(closure, self.covariance, change_points=True, creep=True)
        if shaped.sensor != best.sensor:
            return
        if shaped.shape == "creep":  # still moving: the creep's estimate is its shift now
            best = shaped
        sensor = best.sensor
        shift = float(best.shift_mm[sensor - 1])
        now = stamps[-1]
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

    # ------------------------------------------------------------------ output

    def metrics(self) -> list:
        """Prometheus metric families (:mod:`daemon.recorder.metrics`): per sensor the
        latest test's statistic, estimated offset shift and its standard deviation, and
        whether an alarm stands; the threshold; the poses checked."""
        from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

        st = self.state
        out = [
            CounterMetricFamily("loopcal_loop_closure_poses", "still poses checked for loop "
                                "closure", value=st.poses),  # fmt: skip
            GaugeMetricFamily("loopcal_loop_closure_threshold", "the statistic an alarm needs",
                              value=self.threshold),  # fmt: skip
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
        alarm = GaugeMetricFamily("loopcal_offset_drift_alarm", "1 while an offset_drift alarm "
                                  "stands for the sensor", labels=["sensor"])  # fmt: skip
        for i in range(4):
            alarm.add_metric([str(i + 1)], 1.0 if st.alarm_sensor == i + 1 else 0.0)
        out.append(alarm)
        return out

    def status(self) -> str:
        """A few words for the STATUS line."""
        st = self.state
        if st.alarm_sensor is not None:
            return f"OFFSET DRIFT sensor {st.alarm_sensor} {st.alarm_shift_mm:+.2f} mm"
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
    monitor = HealthMonitor(recorder.controller, recorder.emit, false_alarm=s.health_false_alarm)
    recorder.add_observer(monitor)
    return monitor
