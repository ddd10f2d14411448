"""Time from recording to written controller config: 2 minutes, 1 hour, 24 hours of 20 Hz.

Each recording is a technician's hand moving the simulated shoulder joint (pausing about a
second between moves, 40 mV of noise), written once as the daemon writes it (hourly files,
cached under ``--dir``; scans from :mod:`loopcal.simulator.offline`, the emulator's own) and kept as
the daemon keeps it: each file compacted after its rotation
(:mod:`loopcal.daemon.recording.compact`); the day is also run as written, before compaction (one
chunk a second). The worker fits every usable scan (issue 22; a day thinned to 12,000).
For each length, the median of ``--repeats`` runs of the real command,
``loopcal calibrate DIR --controller-config C --write`` in a subprocess on a fresh config,
and, in this process, where the time goes (read, poses, fit and gates). The baseline,
measured in the same run, is reading the recording alone: the growth of the rest against it
shows how the worker scales. Target (issue #16): a day in under 3 s.

Then a line per stage of the worker with its median over the repeats, a column per
recording (:func:`loopcal.daemon.worker.job.run_worker` on the scans read, the stages timed
where it
calls them): the usable scans (screening, channel skew, thinning), the held-out split and the
gates, the identification (both fits: without the held-out stretches, then all), and the
worker's total; and the command's total, with the share of it
the read takes (the same read, timed in this process).

Run: ``python -m bench.bench_worker [--repeats 3] [--dir bench/results/worker]``.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

import loopcal.calibration.pipeline as pipeline
import loopcal.daemon.worker.job as worker_run
from loopcal.daemon.config.controller import load_controller_config, write_initial_config
from loopcal.daemon.recording import find_recordings, read_recordings
from loopcal.daemon.worker.job import run_worker
from loopcal.daemon.worker.scan_poses import scans_for_fit
from loopcal.simulator.scenarios import HandMoves
from tests.support.recordings import compacted_copy
from tests.support.sessions import PAUSE_S, truth_for, write_session

LENGTHS = {"2 min": 120, "1 h": 3600, "24 h": 86400}


def ensure(directory: Path, seconds: float, seed: int = 9) -> Path:
    if directory.is_dir() and find_recordings(directory):
        return directory
    t = time.perf_counter()
    truth = truth_for(seed)
    write_session(
        directory, HandMoves(seed, params=truth, pause_s=PAUSE_S), truth, seconds, seed=seed
    )
    print(f"  wrote {directory.name}: {time.perf_counter() - t:.0f} s", flush=True)
    return directory


def command(rec_dir: Path, work: Path) -> tuple[float, int]:
    config = write_initial_config(work / "controller.toml", force=True)
    for old in work.glob("controller.toml.*.prev"):
        old.unlink()
    t = time.perf_counter()
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "loopcal.daemon.cli",
            "calibrate",
            str(rec_dir),
            "--controller-config",
            str(config),
            "--write",
        ],
        capture_output=True,
        text=True,
    )
    return time.perf_counter() - t, proc.returncode


#: the worker's stages: the functions timed, where run.py and pipeline.py look them up
STAGE_FUNCTIONS = {
    "poses": [(worker_run, "scans_for_fit")],
    "identification": [(pipeline, "identify")],
    "calibrate": [(worker_run, "calibrate_scans")],
}
STAGE_LABELS = {
    "poses": "usable scans (screen, deskew, thin)",
    "split+gates": "held-out split and gates",
    "identification": "identification (both fits)",
    "worker": "scans+fit+gates (run_worker)",
}


def timed_worker(scans, config) -> tuple[dict[str, float], object]:
    """run_worker on the scans, with the time spent in each stage's functions."""
    spent = dict.fromkeys(STAGE_FUNCTIONS, 0.0)
    originals = []

    def timer(stage, fn):
        def wrapped(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                spent[stage] += time.perf_counter() - t

        return wrapped

    for stage, places in STAGE_FUNCTIONS.items():
        for module, name in places:
            fn = getattr(module, name)
            originals.append((module, name, fn))
            setattr(module, name, timer(stage, fn))
    try:
        t = time.perf_counter()
        res = run_worker(scans, config, config.model())
        total = time.perf_counter() - t
    finally:
        for module, name, fn in originals:
            setattr(module, name, fn)
    out = {
        "poses": spent["poses"],
        "split+gates": total - spent["poses"] - spent["calibrate"],
        "identification": spent["identification"],
        "worker": total,
    }
    return out, res


def stages(rec_dir: Path, work: Path) -> dict[str, float]:
    config = load_controller_config(write_initial_config(work / "c.toml", force=True))
    out: dict[str, float] = {}
    t = time.perf_counter()
    rec = read_recordings(rec_dir)
    out["read"] = time.perf_counter() - t
    t = time.perf_counter()
    usable = scans_for_fit(rec.scans)
    out["poses"] = time.perf_counter() - t
    t = time.perf_counter()
    res = run_worker(rec.scans, config, config.model(), files=rec.files)
    out["poses+fit+gates"] = time.perf_counter() - t
    out["n_poses"] = len(usable)
    out["accepted"] = res.accepted
    out["scans"] = len(rec)
    parts, _ = timed_worker(rec.scans, config)
    out.update({f"stage {k}": v for k, v in parts.items()})
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dir", type=Path, default=Path(__file__).parent / "results" / "worker")
    ap.add_argument("--only", choices=list(LENGTHS), nargs="*", default=list(LENGTHS))
    args = ap.parse_args()
    work = args.dir / "work"
    work.mkdir(parents=True, exist_ok=True)
    print(f"recordings under {args.dir} (written once, cached):")
    rows = []
    runs_of = []
    for label in args.only:  # each as the daemon keeps it (compacted: cached too)
        written = ensure(args.dir / label.replace(" ", ""), LENGTHS[label])
        runs_of.append((label, compacted_copy(written, reuse=True)[0]))
    if "24 h" in args.only:
        runs_of.append(("24 h*", args.dir / "24h"))
    for label, rec_dir in runs_of:
        runs = [command(rec_dir, work) for _ in range(args.repeats)]
        st = [stages(rec_dir, work) for _ in range(args.repeats)]
        keys = ("read", "poses", "poses+fit+gates", *(f"stage {k}" for k in STAGE_LABELS))
        med = {k: statistics.median(s[k] for s in st) for k in keys}
        rows.append((label, statistics.median(t for t, _ in runs), runs[-1][1], med, st[-1]))
    print()
    print(
        f"{'recording':>9} {'scans':>10} {'fitted':>6} {'command':>8} {'read':>7} "
        f"{'usable':>7} {'fit+gates':>9} {'accepted':>8}"
    )
    base = None
    for label, total, rc, med, last in rows:
        fit = med["poses+fit+gates"] - med["poses"]
        print(
            f"{label:>9} {last['scans']:>10,} {last['n_poses']:>6,} {total:7.2f}s "
            f"{med['read']:6.2f}s {med['poses']:6.2f}s {fit:8.2f}s {str(rc == 0):>8}"
        )
        if base is None:
            base = (last["scans"], total)
    print(f"\nby stage (medians of {args.repeats}; the worker in this process):")
    print(f"  {'':<38}" + "".join(f"{label:>9}" for label, *_ in rows))
    for key, text in STAGE_LABELS.items():
        print(f"  {text:<38}" + "".join(f"{med[f'stage {key}']:8.3f}s" for _, _, _, med, _ in rows))
    print(f"  {'the command (loopcal calibrate --write)':<38}" + "".join(
        f"{total:8.3f}s" for _, total, *_ in rows))  # fmt: skip
    print(f"  {'  of which the read (as in this process)':<38}" + "".join(
        f"{med['read']:8.3f}s" for *_, med, _ in rows))  # fmt: skip
    print(f"  {'  the command without the read':<38}" + "".join(
        f"{total - med['read']:8.3f}s" for _, total, _, med, _ in rows))  # fmt: skip
    print("  (* the day as written, before the daemon compacts its files)")
    day = [r for r in rows if r[0] == "24 h"]
    if day:
        t = day[0][1]
        written = [r[1] for r in rows if r[0] == "24 h*"]
        print(
            f"\na day of recording to a written config: {t:.1f} s "
            f"(target < 3 s: {'met' if t < 3 else 'NOT met'}; as written: {written[0]:.1f} s)"
        )
    kept = [r for r in rows if not r[0].endswith("*")]
    if len(kept) > 1 and base is not None:
        (n0, t0), (n1, t1) = base, (kept[-1][4]["scans"], kept[-1][1])
        print(
            f"growth: {n1 / n0:,.0f}x the scans took {t1 / t0:.1f}x the time "
            f"(the command's fixed cost, Python and imports, is in both)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
