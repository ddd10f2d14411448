"""``loopcal fleet`` on Dask: the speed-up from one worker to two on this machine, and what
a task costs Dask beyond its own work.

    python -m bench.bench_fleet [--robots 4] [--days 3] [--minutes 120] [--repeats 3]

A synthetic fleet (``--robots`` robots, ``--days`` days each of ``--minutes`` of a
technician moving the joint, written once under bench/results/fleet) is checked
(``fleet check``'s task: loop closure per robot-day) and summarised (``fleet info``'s):

* baseline: the same tasks one after the other in this process, no Dask;
* a running local cluster of 1 and of 2 worker processes (one thread each, warmed by a
  first task); the speed-up from 1 to 2 (this machine has 2 cores, and other work on it
  shares them), and the same with the start of a local cluster added, as ``loopcal fleet``
  pays it when no ``--scheduler`` is given;
* per-task overhead: the same number of tasks that do nothing (Dask's own cost per
  task: scheduling, pickling, the round trip), and a cluster's start.

Medians of ``--repeats``.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from bench._timing import median_time
from loopcal.daemon.config.controller import write_initial_config
from loopcal.daemon.inspect.fleet import (
    RobotDay,
    check_task,
    info_task,
    robot_days,
    run_on_dask,
)
from loopcal.daemon.live.health import FALSE_ALARM
from loopcal.simulator.scenarios import HandMoves
from tests.support.rows import T0
from tests.support.sessions import PAUSE_S, truth_for, write_session

DAY_NS = 86_400 * 10**9


def make_fleet(root: Path, robots: int, days: int, minutes: float) -> Path:
    marker = root / f".made-{robots}x{days}x{minutes:g}"
    if marker.exists():
        return root
    t = time.perf_counter()
    for k in range(robots):
        truth = truth_for(100 + k)
        d = root / f"robot-{k:03d}"
        for day in range(days):
            write_session(d / "recordings", HandMoves(100 + k + 1000 * day, params=truth,
                                                      pause_s=PAUSE_S),
                          truth, 60 * minutes, seed=100 + k + 1000 * day,
                          hours_per_file=min(1.0, minutes / 60), t0=T0 + day * DAY_NS)  # fmt: skip
        write_initial_config(d / "controller.toml", params=truth)
    marker.touch()
    print(f"wrote the fleet in {time.perf_counter() - t:.0f} s", flush=True)
    return root


def nothing(task: RobotDay) -> dict:
    """A task that does no work: what is left is Dask's cost per task."""
    return {"robot": task.robot, "day": task.day}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--days", type=int, default=3)
    ap.add_argument("--minutes", type=float, default=120.0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--dir", type=Path, default=Path(__file__).parent / "results" / "fleet")
    args = ap.parse_args()
    root = make_fleet(args.dir, args.robots, args.days, args.minutes)
    tasks = robot_days(root)
    print(f"{len(tasks)} robot-days ({args.robots} robots x {args.days} days of "
          f"{args.minutes:g} min); medians of {args.repeats}")  # fmt: skip
    start, _ = median_time(lambda: run_on_dask([], nothing, workers=2), args.repeats)
    from dask.distributed import LocalCluster

    clusters = {w: LocalCluster(n_workers=w, threads_per_worker=1, processes=True,
                                dashboard_address=None, silence_logs=logging.ERROR)
                for w in (1, 2)}  # fmt: skip
    try:
        for w, cluster in clusters.items():  # warm: the workers import numpy and loopcal once
            run_on_dask(tasks[:w], info_task, scheduler=cluster.scheduler_address)
        for name, fn, extra in (("check", check_task, (FALSE_ALARM,)), ("info", info_task, ())):
            base, _ = median_time(lambda fn=fn, extra=extra: [fn(t, *extra) for t in tasks],
                                  args.repeats)  # fmt: skip
            warm = {w: median_time(lambda fn=fn, extra=extra, c=c: run_on_dask(
                        tasks, fn, *extra, scheduler=c.scheduler_address), args.repeats)[0]
                    for w, c in clusters.items()}  # fmt: skip
            cold = {w: t + start for w, t in warm.items()}
            print(f"{name}: in this process {base:.2f} s ({1000 * base / len(tasks):.0f} ms a "
                  f"robot-day); on a running cluster of 1 worker {warm[1]:.2f} s, of 2 workers "
                  f"{warm[2]:.2f} s: speed-up 1 -> 2 workers {warm[1] / warm[2]:.2f}x; with "
                  f"a local cluster started for the run (+{start:.2f} s): "
                  f"{cold[1] / cold[2]:.2f}x")  # fmt: skip
    finally:
        for c in clusters.values():
            c.close()
    many = tasks * 25
    empty, _ = median_time(lambda: run_on_dask(many, nothing, workers=2), args.repeats)
    per_task = (empty - start) / len(many)
    print(f"a local cluster of 2 workers starts and stops in {start:.2f} s; Dask's own cost "
          f"per task (no work, {len(many)} tasks): {1000 * per_task:.2f} ms")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
