"""A month of recordings through ``loopcal info`` and ``loopcal check``: time and peak memory.

    python -m bench.bench_month [--days 30] [--keep-views-days 7] [--dir bench/results/month]

Writes (once, cached) ``--days`` days of 20 Hz recording in hourly files, as the daemon
keeps them: each compacted (chunks of a minute), the newest ``--keep-views-days`` days with
their per-scan views and the older ones without (``[recording].keep_views_days``): a
technician's hand-moved session (:mod:`loopcal.simulator.offline`, 40 mV), one simulated
day repeated with the counters and stamps running on, so every day's scans are distinct.
Then runs the real commands in subprocesses and reports wall time and peak RSS (the
processes' ``ru_maxrss``):

* ``loopcal info DIR --json`` (every file read, still poses searched);
* ``loopcal check DIR --controller-config C --json`` (loop closure over every pose).

Both read one file at a time: the peak RSS must stay that of a file or two (about a
hundred MB), not grow with the month (52 M scans are 2.9 GB as rows).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from loopcal.daemon import recording as rec
from loopcal.daemon.config.controller import write_initial_config
from loopcal.daemon.recording.compact import compact
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.scenarios import HandMoves
from tests.support.recordings import write_rows
from tests.support.rows import rows_from
from tests.support.sessions import PAUSE_S, truth_for

RATE = 20
HOUR = 3600 * RATE
DAY = 24 * HOUR


def make_month(directory: Path, days: int, keep_views_days: int,
               seed: int = 7) -> tuple[Path, Path]:  # fmt: skip
    config = directory / "controller.toml"
    marker = directory / f".made-{days}-views-{keep_views_days}"
    rec_dir = directory / "recordings"
    if marker.exists():
        return rec_dir, config
    rec_dir.mkdir(parents=True, exist_ok=True)
    truth = truth_for(seed)
    t = time.perf_counter()
    t_us, codes = mechanism_scans(HandMoves(seed, params=truth, pause_s=PAUSE_S), truth, DAY,
                                  rate_hz=RATE, noise_volts=0.04, seed=seed)  # fmt: skip
    day_rows = rows_from(t_us, codes)
    print(f"simulated a day in {time.perf_counter() - t:.0f} s", flush=True)
    meta = rec.metadata_records(device={"model": "LDQ412", "scan_rate_hz": str(RATE)},
                                controller={}, command="bench_month")  # fmt: skip
    for d in range(days):
        rows = day_rows.copy()
        rows["counter64"] += np.uint64(d * DAY)
        rows["time64_us"] += np.uint64(d * DAY * 50_000)
        rows["stamp_ns"] += d * DAY * 50_000_000
        rows["host_ns"] += d * DAY * 50_000_000
        for h in range(24):
            part = rows[h * HOUR : (h + 1) * HOUR]
            path = rec_dir / rec.recording_name(int(part["stamp_ns"][0]))
            if path.exists():
                continue
            # ten minutes a write (quick to write), then compacted as the daemon does
            write_rows(path, part, per=600 * RATE, metadata=meta, fsync=False)
            if not compact(path, drop_views=d < days - keep_views_days).done:
                raise SystemExit(f"could not compact {path}")
        print(f"  day {d + 1}/{days} written, {time.perf_counter() - t:.0f} s so far", flush=True)
    write_initial_config(config, force=True, params=truth)
    marker.touch()
    return rec_dir, config


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--days", type=int, default=30)
    ap.add_argument("--keep-views-days", type=int, default=7)
    ap.add_argument("--dir", type=Path, default=Path(__file__).parent / "results" / "month")
    args = ap.parse_args()
    made = (args.dir / f".made-{args.days}-views-{args.keep_views_days}").exists()
    rec_dir, config = make_month(args.dir, args.days, args.keep_views_days)
    if not made:
        # start again, small: a child forked from this process (a simulated day in memory,
        # about half a GB) would count that in its own peak RSS
        sys.stdout.flush()
        os.execv(sys.executable, [sys.executable, "-m", "bench.bench_month", *sys.argv[1:]])
    files = rec.find_recordings(rec_dir)
    size = sum(f.stat().st_size for f in files)
    print(f"{len(files)} files, {size / 1e9:.2f} GB, {args.days * DAY / 1e6:.1f} M scans")
    loopcal = [sys.executable, "-m", "loopcal.daemon.cli"]
    for name, cmd in (
        ("info", [*loopcal, "info", str(rec_dir), "--json"]),
        ("check", [*loopcal, "check", str(rec_dir), "--controller-config", str(config),
                   "--json"]),
    ):  # fmt: skip
        wall, rss, doc = run_measured(cmd)
        what = (f"{doc['scans']:,} scans, {doc['poses']:,} poses" if name == "info"
                else f"{doc['poses']:,} poses, {len(doc['changes'])} change(s)")  # fmt: skip
        print(f"loopcal {name} of {args.days} days: {wall:.0f} s ({wall / args.days:.1f} s a "
              f"day), peak RSS {rss:.0f} MB; {what}", flush=True)  # fmt: skip
    return 0


def run_measured(cmd: list[str]) -> tuple[float, float, dict]:
    """(wall s, peak RSS MB, printed JSON) of a command in a fresh process."""
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    out = proc.stdout.read()
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    code = os.waitstatus_to_exitcode(status)
    if code not in (0, 1):
        raise SystemExit(f"{' '.join(cmd)} failed ({code}):\n{err}")
    return wall, usage.ru_maxrss / 1024, json.loads(out)


if __name__ == "__main__":
    sys.exit(main())
