"""Loop-closure health (:mod:`loopcal.daemon.live.health`): false alarms, detection delay, cost.

The monitor is fed a technician's hand-moved session (pausing about a second between
moves, 40 mV of noise, a mechanism whose offsets are up to 3 mm off nominal) a quarter
second (5 scans) at a time, as the recorder feeds it, at a controller config equal to the
truth. Scans are :mod:`loopcal.simulator.offline`'s, the emulator's own, bit for bit.

* ``clean``: ``--hours`` of clean data for each of ``--seeds`` seeds (1, 2, ...): poses
  checked and alarms raised, against the baseline the threshold states, the expected number
  of false alarms (poses x false-alarm probability per pose); the largest statistic seen as
  a fraction of the threshold (the headroom); the CPU time per hour of data, which is the
  monitor's cost in the daemon (as a share of one core).
* ``detect``: a 0.5 mm step, a -0.5 mm step and a 1 mm/min creep of each sensor's offset
  from 120 s, over ``--seeds`` seeds (10, 11, ...), 420 s each: delay from the drift's start
  to the first ``offset_drift`` event (device time of the last scan fed when it fired),
  whether it names the right sensor, and its estimated shift against the true one at that
  moment (each run stops at that alarm). Medians, maxima and 90th percentiles.
* ``live`` (not in the default set): the real path end to end, ``loopcal simulate``
  (seed 3, ``--fault offset@600:2=+0.5``, 20x speed) read by ``loopcal record`` at a
  controller config with the truth's values; alarms before the fault (must be none) and the
  first after it, from the recording's events (its device time: the newest scan received
  when it was raised); baseline: the same scans fed offline. The daemon's own lag (a FIFO
  read every 0.5 s, the monitor fed every second) is multiplied by the speed in device time.

Run: ``python -m bench.bench_health [--part clean detect live] [--hours 1] [--seeds N]``.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from loopcal.calibration.parameters import NAMES
from loopcal.daemon.config.controller import nominal_config, write_initial_config
from loopcal.daemon.live.health import HealthMonitor
from loopcal.daemon.recording import read_recordings
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.scenarios import HandMoves
from tests.support.processes import Proc, listening_url
from tests.support.rows import rows_from
from tests.support.sessions import PAUSE_S, truth_for

LOOPCAL = [sys.executable, "-m", "loopcal.daemon.cli"]
RATE = 20
NOISE_V = 0.04
FEED = 5  # scans per feed: a quarter second, as the recorder hands them on
DRIFT_AT = 120.0
DETECT_S = 420
DRIFTS = {"step +0.5 mm": ("step", 0.5), "step -0.5 mm": ("step", -0.5),
          "creep 1 mm/min": ("creep", 1.0)}  # fmt: skip


@dataclass
class Run:
    """One session through a monitor: events as (device s, kind, details)."""

    monitor: HealthMonitor
    events: list[tuple[float, str, dict]] = field(default_factory=list)
    max_ratio: float = 0.0  # largest statistic of any test / threshold
    cpu_s: float = 0.0  # process time spent in feed()
    seconds: float = 0.0  # device time fed


def run_monitor(
    seed: int,
    seconds: float,
    drifts: tuple[OffsetDrift, ...] = (),
    *,
    stop_after: float | None = None,
) -> Run:
    """Feed ``seconds`` of a hand-moved session (truth_for(seed)) to a monitor whose config
    is the truth, FEED scans at a time; stop at the first alarm at or after ``stop_after``
    s, if given."""
    truth = truth_for(seed)
    scenario = HandMoves(seed, params=truth, pause_s=PAUSE_S)
    t_us, codes = mechanism_scans(
        scenario, truth, round(RATE * seconds), rate_hz=RATE, noise_volts=NOISE_V, seed=seed,
        drifts=drifts,
    )  # fmt: skip
    rows = rows_from(t_us, codes)
    clock = [0.0]
    events: list[tuple[float, str, dict]] = []
    mon = HealthMonitor(
        replace(nominal_config(), params=tuple(truth)),
        lambda kind, level, msg, **d: events.append((clock[0], kind, d)),
    )
    run = Run(mon, events)
    last = None
    cpu = 0.0
    for a in range(0, len(rows), FEED):
        b = min(a + FEED, len(rows))
        clock[0] = t_us[b - 1] / 1e6
        t0 = time.process_time()
        mon.feed(rows[a:b])
        cpu += time.process_time() - t0
        if mon.state.last is not None and mon.state.last is not last:
            last = mon.state.last
            run.max_ratio = max(run.max_ratio, float(np.max(last.statistic)) / mon.threshold)
        if stop_after is not None and any(
            k == "offset_drift" and t >= stop_after for t, k, _ in events
        ):
            break
    run.cpu_s, run.seconds = cpu, clock[0]
    return run


def pct(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


def fmt(x: float, spec: str = ".0f", width: int = 0) -> str:
    return ("-" if x != x else format(x, spec)).rjust(width)  # NaN: nothing to show


# ---------------------------------------------------------------------------- clean


def part_clean(hours: float, seeds: list[int]) -> None:
    print(f"== clean: {hours:g} h of hand-moved data per seed, config = truth, 40 mV")
    print(
        f"{'seed':>4} {'hours':>5} {'poses':>6} {'alarms':>6} {'max T/thr':>9} "
        f"{'CPU s':>6} {'CPU s/h':>7} {'% core':>6}"
    )
    runs = []
    for seed in seeds:
        r = run_monitor(seed, hours * 3600)
        alarms = sum(k == "offset_drift" for _, k, _ in r.events)
        h = r.seconds / 3600
        print(
            f"{seed:>4} {h:5.2f} {r.monitor.state.poses:>6,} {alarms:>6} {r.max_ratio:9.3f} "
            f"{r.cpu_s:6.1f} {r.cpu_s / h:7.1f} {100 * r.cpu_s / h / 3600:5.2f}%",
            flush=True,
        )
        runs.append((r, alarms, h))
    mon = runs[0][0].monitor
    poses = sum(r.monitor.state.poses for r, _, _ in runs)
    alarms = sum(a for _, a, _ in runs)
    h = sum(h for _, _, h in runs)
    cpu_h = sum(r.cpu_s for r, _, _ in runs) / h
    print(
        f"total: {h:.2f} h, {poses:,} poses checked ({poses / h:,.0f} per hour), "
        f"{alarms} alarm(s) (must be 0: {'ok' if alarms == 0 else 'FALSE ALARM'})"
    )
    print(
        f"threshold {mon.threshold:.2f} (false-alarm probability {mon.false_alarm:g} per pose; "
        f"Bonferroni over 4 sensors x 30 change points): expected false alarms "
        f"{poses * mon.false_alarm:.1e}"
    )
    print(
        f"largest statistic seen: {max(r.max_ratio for r, _, _ in runs):.3f} x the threshold "
        f"(median over seeds {statistics.median(r.max_ratio for r, _, _ in runs):.3f})"
    )
    print(
        f"cost: {cpu_h:.1f} CPU s per hour of data = {100 * cpu_h / 3600:.2f} % of one core "
        "(process time inside feed(), all seeds together)"
    )


# ---------------------------------------------------------------------------- detect


@dataclass
class Detection:
    kind: str
    sensor: int
    seed: int
    early: int  # alarms before the drift started (false alarms)
    delay: float | None  # s from the drift's start to the first alarm after it
    named: int | None  # the sensor that alarm named
    shift: float | None  # its estimated shift, mm
    true_shift: float | None  # the drift's shift at that moment, mm
    shape: str = ""  # the shape the alarm's test found (step or creep)
    poses: int = 0  # poses that test left shifted


def detect_one(label: str, sensor: int, seed: int) -> Detection:
    kind, amount = DRIFTS[label]
    drift = OffsetDrift(kind, sensor, DRIFT_AT, amount)
    r = run_monitor(seed, DETECT_S, (drift,), stop_after=DRIFT_AT)
    alarms = [(t, d) for t, k, d in r.events if k == "offset_drift"]
    early = [a for a in alarms if a[0] < DRIFT_AT]
    late = [a for a in alarms if a[0] >= DRIFT_AT]
    if not late:
        return Detection(label, sensor, seed, len(early), None, None, None, None)
    t, d = late[0]
    true = float(drift.shift_mm(np.array(t)))
    return Detection(
        label, sensor, seed, len(early), t - DRIFT_AT, d["sensor"], d["shift_mm"], true,
        d["shape"], d["poses"],
    )  # fmt: skip


def part_detect(seeds: list[int]) -> None:
    print(
        f"== detect: drift from {DRIFT_AT:g} s, {DETECT_S} s per run, seeds "
        f"{seeds[0]}..{seeds[-1]} ({len(seeds)}); delay = device time of the last scan fed "
        "when the first offset_drift fired, minus the drift's start"
    )
    results: list[Detection] = []
    t0 = time.perf_counter()
    for label in DRIFTS:
        for sensor in (1, 2, 3, 4):
            for seed in seeds:
                results.append(detect_one(label, sensor, seed))
    wall = time.perf_counter() - t0
    print(
        f"{'drift':>15} {'sensor':>6} {'correct':>7} {'wrong':>5} {'missed':>6} {'early':>5} "
        f"{'median s':>8} {'max s':>6} {'est. mm':>7} {'true mm':>7}"
    )
    for label in DRIFTS:
        for sensor in (1, 2, 3, 4):
            rs = [r for r in results if r.kind == label and r.sensor == sensor]
            hit = [r for r in rs if r.delay is not None]
            delays = [r.delay for r in hit]
            print(
                f"{label:>15} {sensor:>6} {sum(r.named == sensor for r in hit):>4}/{len(rs):<2} "
                f"{sum(r.named != sensor for r in hit):>5} {len(rs) - len(hit):>6} "
                f"{sum(r.early for r in rs):>5} "
                f"{fmt(pct(delays, 50), '.1f', 8)} {fmt(pct(delays, 100), '.1f', 6)} "
                f"{fmt(pct([r.shift for r in hit], 50), '+.2f', 7)} "
                f"{fmt(pct([r.true_shift for r in hit], 50), '+.2f', 7)}"
            )
    print()
    for label in DRIFTS:
        rs = [r for r in results if r.kind == label]
        hit = [r for r in rs if r.delay is not None]
        delays = [r.delay for r in hit]
        correct = sum(r.named == r.sensor for r in hit)
        err = [abs(r.shift - r.true_shift) for r in hit]
        print(
            f"{label}: {correct}/{len(rs)} correct, {len(hit) - correct} wrong sensor, "
            f"{len(rs) - len(hit)} missed, {sum(r.early for r in rs)} false alarm(s) before "
            f"the drift; delay median {fmt(pct(delays, 50), '.1f')} s, "
            f"90th percentile {fmt(pct(delays, 90), '.1f')} s, max "
            f"{fmt(pct(delays, 100), '.1f')} s; "
            f"|est. - true shift| median {fmt(pct(err, 50), '.2f')} mm; test shape "
            f"{sum(r.shape == 'step' for r in hit)} step, {sum(r.shape == 'creep' for r in hit)} "
            f"creep; shifted poses median {fmt(pct([r.poses for r in hit], 50), '.0f')}"
        )
    bad = [r for r in results if r.delay is None or r.named != r.sensor or r.early]
    for r in bad:
        print(
            f"  ! {r.kind} sensor {r.sensor} seed {r.seed}: "
            + ("missed" if r.delay is None else f"named sensor {r.named} after {r.delay:.1f} s")
            + (f", {r.early} alarm(s) before the drift" if r.early else "")
        )
    print(f"({len(results)} runs in {wall:.0f} s)")


# ---------------------------------------------------------------------------- live


def part_live(speed: float, fault_at: float, after: float, seed: int = 3) -> None:
    truth = truth_for(seed)
    every = ",".join(f"{n}={float(truth[i])!r}" for i, n in enumerate(NAMES))
    duration = (fault_at + after) / speed
    fault = f"offset@{fault_at:g}:2=+0.5"
    print(
        f"== live: loopcal simulate --speed {speed:g} --seed {seed} --fault {fault} -> "
        f"loopcal record --duration {duration:g} (wall s), controller config = truth"
    )
    with tempfile.TemporaryDirectory(prefix="bench-health-") as tmp:
        work = Path(tmp)
        config = write_initial_config(work / "controller.toml", params=truth)
        sim = Proc(
            ["simulate", "--speed", f"{speed:g}", "--wait-for-client", "--pause",
             f"{PAUSE_S[0]},{PAUSE_S[1]}", "--seed", str(seed), "--truth", every,
             "--fault", fault]
        )  # fmt: skip
        try:
            url = listening_url(sim, timeout=30)
            out = work / "rec"
            t0 = time.perf_counter()
            proc = subprocess.run(
                [*LOOPCAL, "record", "--daq", url, "--out", str(out), "--controller-config",
                 str(config), "--duration", f"{duration:g}"],
                capture_output=True, text=True, timeout=duration + 120,
            )  # fmt: skip
            wall = time.perf_counter() - t0
        finally:
            sim.stop()
            sim.kill()
        if proc.returncode != 0:
            print(f"loopcal record exited {proc.returncode}:\n{proc.stdout}{proc.stderr}")
            return
        rec = read_recordings(out)
    scans = rec.scans
    dev = scans["time64_us"] / 1e6
    host = scans["host_ns"]
    lost = sum(len(rec.events_of(k)) for k in ("gap", "overflow", "disconnect"))
    print(
        f"recorded {len(scans):,} scans, device time {dev[0]:.1f}..{dev[-1]:.1f} s, "
        f"in {wall:.1f} s wall (the command, with start-up); gap/overflow/disconnect events: {lost}"
    )

    def device_s(stamp_ns: int) -> float:
        """Device time of the newest scan received when the event was raised."""
        k = int(np.searchsorted(host, stamp_ns, side="right")) - 1
        return float(dev[max(k, 0)])

    alarms = rec.events_of("offset_drift")
    cleared = rec.events_of("offset_drift_cleared")
    before = [e for e in alarms if device_s(e.stamp_ns) < fault_at]
    after_ = [e for e in alarms if device_s(e.stamp_ns) >= fault_at]
    print(
        f"offset_drift events: {len(alarms)} ({len(before)} before the fault at {fault_at:g} s: "
        f"{'ok' if not before else 'FALSE ALARM'}); offset_drift_cleared: {len(cleared)}"
    )
    for e in before:
        print(f"  ! before the fault at {device_s(e.stamp_ns):.1f} s: {e.message}")
    if not after_:
        print(f"no alarm within {dev[-1] - fault_at:.0f} device s after the fault: MISSED")
        return
    e = after_[0]
    t = device_s(e.stamp_ns)
    by_wall = dev[0] + (e.stamp_ns - host[0]) / 1e9 * speed
    d = e.details
    print(
        f"first alarm after the fault: {t - fault_at:.1f} device s after it (newest scan "
        f"received; by wall time x speed {by_wall - fault_at:.1f} s), sensor {d['sensor']} "
        f"({'right' if d['sensor'] == 2 else 'WRONG'}), shift {d['shift_mm']:+.3f} "
        f"+- {d['std_mm']:.3f} mm (true +0.5), statistic {d['statistic']:.1f} "
        f"(threshold {d['threshold']:.1f}), {d['poses']} poses, {d['shape']}"
    )
    print(f"  message: {e.message}")
    # the same scans offline (bit-identical), fed a quarter second at a time
    drift = OffsetDrift("step", 2, fault_at, 0.5)
    r = run_monitor(seed, fault_at + after, (drift,), stop_after=fault_at)
    off = [(t, d) for t, k, d in r.events if k == "offset_drift"]
    if off:
        t, d = off[0]
        print(
            f"offline, the same scans: first alarm {t - fault_at:.1f} s after the fault, sensor "
            f"{d['sensor']}, shift {d['shift_mm']:+.3f} mm, statistic {d['statistic']:.1f}"
        )
        print(
            f"live - offline: {(device_s(e.stamp_ns) - t):+.1f} device s = "
            f"{(device_s(e.stamp_ns) - t) / speed:+.2f} wall s (FIFO read every 0.5 s, "
            f"the monitor fed every second: up to ~1.5 wall s, x{speed:g} in device time)"
        )
    else:
        print("offline, the same scans: no alarm")


# ---------------------------------------------------------------------------- main


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--part", choices=("clean", "detect", "live"), nargs="+", default=["clean", "detect"]
    )
    ap.add_argument("--hours", type=float, default=1.0, help="clean: hours per seed (1)")
    ap.add_argument(
        "--seeds",
        type=int,
        default=None,
        help="number of seeds (clean: 3 from 1; detect: 8 from 10)",
    )
    ap.add_argument("--speed", type=float, default=20.0, help="live: emulator speed (20)")
    ap.add_argument("--fault-at", type=float, default=600.0, help="live: device s (600)")
    ap.add_argument(
        "--after", type=float, default=120.0, help="live: device s recorded after the fault"
    )
    args = ap.parse_args()
    if "clean" in args.part:
        part_clean(args.hours, list(range(1, 1 + (args.seeds or 3))))
        print()
    if "detect" in args.part:
        part_detect(list(range(10, 10 + (args.seeds or 8))))
        print()
    if "live" in args.part:
        part_live(args.speed, args.fault_at, args.after)
    return 0


if __name__ == "__main__":
    sys.exit(main())
