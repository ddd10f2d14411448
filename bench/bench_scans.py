"""Every scan against still poses: the worker's fit on the whole hand motion (one plate
rotation per scan, the channel skew corrected) side by side with the still-pose method it
replaced, on the same simulated technician sessions.

Each session is a technician's hand moving the simulated shoulder joint (pausing about a
second between moves, 40 mV of noise, 12-bit codes, channels converted 250 µs apart: the
offline emulator's scans, :func:`tests.support.sessions.hand_rows`), of a mechanism whose
offsets and geometry are off the blueprint (:func:`tests.support.sessions.truth_for`). The
same worker code runs on each (:func:`loopcal.daemon.worker.run.run_worker`), from the
reference config, the paper's seven free parameters:

``mc``: per parameter, the RMS error over ``--sessions`` sessions of

* ``poses``: still poses, averaged, 50 selected (the method before issue 22), 120 s;
* ``scans``: every usable scan, 120 s, and ``scans 75s``: the first 75 s of the same
  sessions;
* ``no deskew``: every scan, 120 s, the channel skew ignored;

the ratio of ``scans`` to ``poses`` (target <= 0.78 for every parameter), ``scans 75s``
against ``poses`` at 120 s (target <= 1), the RMS of error / reported std per parameter
(target 0.9 to 1.15), what ignoring the skew costs (mean error over its standard error, per
parameter), and how many sessions each accepts. Baseline: ``poses`` in the same run.

``gains``: sensor 3's gain in the config off by 0 .. 3 % on ``--gain-sessions`` sessions:
how many each method refuses, through which gate, and the largest |error| / std of the
seven parameters among the sessions it accepts; and, with the four gains free too (every
scan), the same and the gains' precision.

``enough``: ``record --until-enough`` on ``--enough-sessions`` simulated technicians (up
to 5 minutes each): the guidance's own rule (the worker accepts and every offset's
standard deviation is at most 0.1 mm, judged once a second) with every scan against still
poses: when each stops (median and quartiles), how many reach it within 5 minutes, and the
RMS error of the offsets at the stop. Target: every scan stops at least 30 % sooner, with
the same acceptance.

``thin``: an hour of hand motion (72,000 scans): the fit on every usable scan against the
worker's thinning to :data:`~loopcal.daemon.worker.motion.MAX_FIT_SCANS` (12,000): the
reported standard deviations (the precision the thinning costs) and the time.

Run: ``python -m bench.bench_scans [--part mc|gains|enough|thin] [--sessions 40]
[--gain-sessions 10] [--enough-sessions 20] [--jobs 2]``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import time
from dataclasses import replace

import numpy as np

from loopcal.calibration.parameters import INDEX, PAPER7, ParameterModel
from loopcal.calibration.pipeline import calibrate_scans
from loopcal.daemon.config.controller import ControllerConfig, nominal_config
from loopcal.daemon.worker.motion import scans_for_fit
from loopcal.daemon.worker.run import run_worker
from tests.support.sessions import hand_rows, truth_for

FREE = list(PAPER7.free)
GAINS = ("S1", "S2", "S3", "S4")
WITH_GAINS = ParameterModel(free=(*PAPER7.free, *GAINS), ties=PAPER7.ties)
IDX = [INDEX[n] for n in FREE]
VARIANTS = ("poses", "scans", "scans 75s", "no deskew")


def reference_config() -> ControllerConfig:
    return nominal_config()


def _errors(params: np.ndarray, std: dict, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    err = params[IDX] - truth[IDX]
    return err, err / np.array([std.get(n, np.nan) for n in FREE])


def no_deskew(rows: np.ndarray, config: ControllerConfig) -> tuple[np.ndarray, dict, bool]:
    """The worker's final fit on every usable scan, the skew left in."""
    S = scans_for_fit(rows, skew_s=0.0)
    ident = calibrate_scans(S.volts, PAPER7, np.array(config.params)).identification
    return ident.params, dict(zip(FREE, ident.std, strict=True)), True


def one_session(seed: int) -> dict:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    config = reference_config()
    truth = truth_for(seed)
    rows = hand_rows(2400, seed=seed)
    out = {}
    for name in VARIANTS:
        t = time.perf_counter()
        if name == "no deskew":
            params, std, accepted = no_deskew(rows, config)
        else:
            r = run_worker(
                rows[:1500] if name == "scans 75s" else rows, config, PAPER7,
                samples="poses" if name == "poses" else "scans",
            )  # fmt: skip
            params, std, accepted = r.params, r.std, r.accepted
        err, z = _errors(params, std, truth)
        out[name] = {"err": err, "z": z, "std": err / z, "accepted": accepted,
                     "s": time.perf_counter() - t}  # fmt: skip
    return out


def _pool(jobs: int):
    return mp.get_context("spawn").Pool(jobs)


def part_mc(sessions: int, jobs: int) -> None:
    t0 = time.perf_counter()
    with _pool(jobs) as pool:
        runs = pool.map(one_session, range(1, sessions + 1))
    print(f"mc: {sessions} two-minute hand sessions at 40 mV, {time.perf_counter() - t0:.0f} s")
    rms = {}
    for v in VARIANTS:
        err = np.array([r[v]["err"] for r in runs])
        rms[v] = np.sqrt(np.nanmean(err**2, axis=0))
    head = f"{'':24}" + "".join(f"{n:>8}" for n in FREE)
    print(head)
    for v in VARIANTS:
        print(f"{'RMS error ' + v:24}" + "".join(f"{x:8.4f}" for x in rms[v]))
    ratio = rms["scans"] / rms["poses"]
    ratio75 = rms["scans 75s"] / rms["poses"]
    print(f"{'scans / poses':24}" + "".join(f"{x:8.2f}" for x in ratio)
          + f"   target <= 0.78: {'met' if ratio.max() <= 0.78 else 'NOT met'}")  # fmt: skip
    print(f"{'scans 75s / poses 120s':24}" + "".join(f"{x:8.2f}" for x in ratio75)
          + f"   target <= 1: {'met' if ratio75.max() <= 1.0 else 'NOT met'}")  # fmt: skip
    # the same ratios without the sampling noise of 40 errors: the reported standard
    # deviations (honest, below), median over the sessions of each session's ratio
    for v in ("scans", "scans 75s"):
        r = np.median(np.array([x[v]["std"] / x["poses"]["std"] for x in runs]), axis=0)
        print(f"{'std ' + v + ' / poses':24}" + "".join(f"{x:8.2f}" for x in r))
    for v in VARIANTS:
        z = np.array([r[v]["z"] for r in runs])
        rz = np.sqrt(np.nanmean(z**2, axis=0))
        ok = "" if v != "scans" else (
            f"   target 0.9..1.15: {'met' if rz.min() >= 0.9 and rz.max() <= 1.15 else 'NOT met'}"
        )
        print(f"{'RMS err/std ' + v:24}" + "".join(f"{x:8.2f}" for x in rz) + ok)
    # what ignoring the skew costs: the mean error, in standard errors, and in stds
    d = np.array([r["no deskew"]["err"] for r in runs])
    zs = np.array([r["no deskew"]["z"] for r in runs])
    k = len(runs)
    print(f"{'no deskew mean err/SE':24}"
          + "".join(f"{x:8.2f}" for x in d.mean(0) / (d.std(0, ddof=1) / np.sqrt(k))))  # fmt: skip
    print(f"{'no deskew mean err/std':24}" + "".join(f"{x:8.3f}" for x in zs.mean(0)))
    dz = np.array([r["no deskew"]["z"] - r["scans"]["z"] for r in runs])
    print(f"{'skew shift/std median':24}" + "".join(f"{x:8.3f}" for x in np.median(np.abs(dz), 0))
          + f"   worst {np.abs(dz).max():.3f}")  # fmt: skip
    for v in VARIANTS:
        acc = sum(r[v]["accepted"] for r in runs)
        secs = np.median([r[v]["s"] for r in runs])
        print(f"accepted {v:12}: {acc}/{k}   worker median {1000 * secs:.0f} ms")


def one_gain(args: tuple[int, float]) -> dict:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    seed, off = args
    config = reference_config()
    p = np.array(config.params)
    p[INDEX["S3"]] *= 1.0 + off
    config = replace(config, params=p)
    truth = truth_for(seed)
    rows = hand_rows(2400, seed=seed)
    out = {}
    for samples in ("poses", "scans"):
        r = run_worker(rows, config, PAPER7, samples=samples)
        _, z = _errors(r.params, r.std, truth)
        out[samples] = (r.accepted, [g.name for g in r.failed], float(np.abs(z).max()))
    # every scan with the four gains free too: the seven's error over their std, and the
    # gains' std
    r = run_worker(rows, config, WITH_GAINS)
    _, z = _errors(r.params, r.std, truth)
    out["scans, gains free"] = (r.accepted, [g.name for g in r.failed], float(np.abs(z).max()),
                                max(r.std.get(n, np.nan) for n in GAINS))  # fmt: skip
    return out


def part_gains(sessions: int, jobs: int) -> None:
    offs = (0.0, 0.0025, 0.005, 0.01, 0.02, 0.03)
    with _pool(jobs) as pool:
        res = pool.map(one_gain, [(s, o) for o in offs for s in range(1, sessions + 1)])
    print(f"gains: S3 in the config off by ..., {sessions} sessions each")
    print(f"{'S3 off':>7} {'method':>6} {'refused':>8} {'by':>40} {'max |err|/std accepted':>24}"
          "  (the seven's)")  # fmt: skip
    for j, off in enumerate(offs):
        chunk = res[j * sessions : (j + 1) * sessions]
        for m in ("poses", "scans", "scans, gains free"):
            refused = [c[m] for c in chunk if not c[m][0]]
            by: dict[str, int] = {}
            for _, names, *_ in refused:
                for n in names:
                    by[n] = by.get(n, 0) + 1
            # gains free: every session (the precision gate refuses two minutes of them)
            acc = [c[m][2] for c in chunk if c[m][0] or m == "scans, gains free"]
            worst = f"{max(acc):.2f}" if acc else "-"
            text = ", ".join(f"{n} {c}" for n, c in sorted(by.items()))
            print(f"{100 * off:6.2f}% {m:>6} {len(refused):>4}/{sessions:<3} {text:>40} "
                  f"{worst:>24}")  # fmt: skip
        g = [c["scans, gains free"][3] for c in chunk]
        print(f"{'':8}gains free: largest std of S1..S4 {np.median(g):.4f} mm/V (median)")


#: the guidance's target on every offset's standard deviation, mm, and the longest session
ENOUGH_MM, LONGEST_S = 0.1, 300


def _enough(rows: np.ndarray, config: ControllerConfig, samples: str, truth: np.ndarray):
    """(stop time s or None, offsets' errors at the stop) under the guidance's rule, judged
    every second: first in 5-s steps, then second by second within the step that got there."""
    offsets = [INDEX[n] for n in ("d01", "d02", "d03", "d04")]

    def ok(t: int):
        r = run_worker(rows[: 20 * t], config, PAPER7, samples=samples)
        good = r.accepted and all(r.std[n] <= ENOUGH_MM for n in ("d01", "d02", "d03", "d04"))
        return good, r

    for t in range(10, LONGEST_S + 1, 5):
        good, r = ok(t)
        if good:
            for u in range(max(t - 4, 10), t):
                good_u, r_u = ok(u)
                if good_u:
                    return u, r_u.params[offsets] - truth[offsets]
            return t, r.params[offsets] - truth[offsets]
    return None, None


def one_enough(seed: int) -> dict:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    config = reference_config()
    truth = truth_for(seed)
    rows = hand_rows(20 * LONGEST_S, seed=seed)
    return {m: _enough(rows, config, m, truth) for m in ("poses", "scans")}


def part_enough(sessions: int, jobs: int) -> None:
    t0 = time.perf_counter()
    with _pool(jobs) as pool:
        res = pool.map(one_enough, range(101, 101 + sessions))
    print(f"enough: {sessions} technicians, --until-enough at {ENOUGH_MM} mm on the offsets, "
          f"at most {LONGEST_S} s ({time.perf_counter() - t0:.0f} s)")  # fmt: skip
    stops = {}
    for m in ("poses", "scans"):
        t = [r[m][0] for r in res if r[m][0] is not None]
        e = np.array([r[m][1] for r in res if r[m][0] is not None])
        stops[m] = np.array(t, dtype=float)
        q = np.percentile(t, [25, 50, 75]) if t else [np.nan] * 3
        rms = np.sqrt(np.mean(e**2)) if len(e) else np.nan
        print(f"  {m:6}: enough in {len(t)}/{sessions}; stop at {q[1]:.0f} s (quartiles {q[0]:.0f}"
              f"..{q[2]:.0f} s); offsets' RMS error at the stop {rms:.3f} mm")  # fmt: skip
    both = [(r["poses"][0], r["scans"][0]) for r in res
            if None not in (r["poses"][0], r["scans"][0])]  # fmt: skip
    if both:
        ratio = np.median([b / a for a, b in both])
        print(f"  every scan stops after {ratio:.2f} of the still-pose time (median of "
              f"{len(both)} paired sessions; target <= 0.70: "
              f"{'met' if ratio <= 0.7 else 'NOT met'})")  # fmt: skip


def part_thin() -> None:
    from loopcal.calibration.identify import identify

    rows = hand_rows(72_000, seed=9)
    start = np.array(reference_config().params)
    S_all = scans_for_fit(rows, max_scans=10**9)
    S = scans_for_fit(rows)
    out = {}
    for name, s in (("every scan", S_all), (f"every {S.stride}th", S)):
        t = time.perf_counter()
        ident = identify(s.volts, PAPER7, start, method="ml")
        out[name] = (ident.std, time.perf_counter() - t, len(s))
    print("thin: an hour of hand motion (72,000 scans)")
    print(f"{'':22}" + "".join(f"{n:>8}" for n in FREE) + f"{'scans':>8}{'fit s':>8}")
    for name, (std, secs, n) in out.items():
        print(f"{'std ' + name:22}" + "".join(f"{x:8.4f}" for x in std) + f"{n:8d}{secs:8.2f}")
    a, b = (v[0] for v in out.values())
    print(f"{'ratio':22}" + "".join(f"{x:8.2f}" for x in b / a))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--part", choices=("mc", "gains", "enough", "thin"))
    ap.add_argument("--enough-sessions", type=int, default=20)
    ap.add_argument("--sessions", type=int, default=40)
    ap.add_argument("--gain-sessions", type=int, default=10)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    if args.part in (None, "mc"):
        part_mc(args.sessions, args.jobs)
    if args.part in (None, "gains"):
        part_gains(args.gain_sessions, args.jobs)
    if args.part in (None, "enough"):
        part_enough(args.enough_sessions, args.jobs)
    if args.part in (None, "thin"):
        part_thin()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
