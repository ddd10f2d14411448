"""``loopcal fleet info|check ROOT ... [--table FILE] [--json] [--scheduler ADDRESS]``:
``loopcal info`` and ``loopcal check`` over a fleet's archives, one task per robot and UTC
day, on Dask (:mod:`loopcal.daemon.inspect.fleet`; ``pip install loopcal[fleet]``).

ROOT holds a directory per robot, each with its controller config (``controller.toml``) and
its recordings (directly, or in ``recordings/``). The tasks run on a local cluster of
``--workers`` processes, or on a running Dask scheduler (``--scheduler tcp://host:8786``:
the workers must see the same paths). Progress goes to stderr; the table (one row per
robot-day) to ``--table`` (CSV, or Parquet for a ``.parquet`` name), or to stdout as CSV, or
with ``--json`` as one JSON object ``{"columns": [...], "rows": [{column: value}, ...]}``.
``fleet check``'s ``proposals`` column holds what the daemon's upkeep would propose from the
robot-day (``d03 +0.80``: the offset and its shift, mm; ``-``: nothing).
Exit status: 0, 1 if ``fleet check`` found a change or a recalibration would be proposed,
2 for bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from ..arguments import path_argument
from ..inspect.fleet import CONFIG_NAME
from .check import add_false_alarm_option, add_upkeep_options, check_false_alarm, upkeep_settings
from .errors import CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", choices=("info", "check"), help="info: what the archives hold; "
                   "check: did each robot's loops close at its controller config")  # fmt: skip
    p.add_argument("roots", nargs="+", type=path_argument, metavar="ROOT",
                   help="fleet roots: a directory per robot")  # fmt: skip
    p.add_argument("--table", type=path_argument, metavar="FILE",
                   help="write the table to FILE (.csv or .parquet; default: CSV on "
                        "stdout)")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help='the table as one JSON object on stdout: {"columns": [...], "rows": '
                        "[...]}")  # fmt: skip
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="a running Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a local "
                        "cluster)")  # fmt: skip
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="processes of the local cluster (default 2)")  # fmt: skip
    p.add_argument("--config-name", default=CONFIG_NAME, metavar="NAME",
                   help=f"each robot's controller config file (default {CONFIG_NAME})")  # fmt: skip
    add_false_alarm_option(p, what="check: ")
    add_upkeep_options(p, what="check: ")


def run(args: argparse.Namespace) -> int:
    try:
        import dask.distributed  # noqa: F401 - the optional extra
    except ImportError:
        raise CommandError("Dask is not installed: pip install 'loopcal[fleet]'") from None
    from ..inspect.fleet import (
        CHECK_COLUMNS,
        INFO_COLUMNS,
        check_task,
        info_task,
        robot_days,
        run_on_dask,
        table_columns,
        write_table,
    )

    if args.workers < 1:
        raise CommandError(f"--workers {args.workers}: at least 1")
    check_false_alarm(args.false_alarm)
    upkeep = upkeep_settings(args)
    if args.table is not None and args.json:
        raise CommandError("give --table or --json, not both")
    if args.table is not None and not args.table.parent.is_dir():
        raise CommandError(f"--table {args.table}: directory {args.table.parent} does not "
                           "exist")  # fmt: skip
    try:
        tasks = [t for root in args.roots for t in robot_days(root, args.config_name)]
    except OSError as exc:
        raise CommandError(exc) from None
    n_robots = len({t.robot for t in tasks})
    where = args.scheduler or f"a local cluster of {args.workers} worker(s)"
    print(f"{len(tasks)} robot-days of {n_robots} robot(s) on {where}", file=sys.stderr)

    tty = sys.stderr.isatty()
    step = max(1, len(tasks) // 10)

    def progress(done: int, total: int, elapsed: float) -> None:
        if tty:  # one line, redrawn
            print(f"\r{done}/{total} robot-days done, {elapsed:.1f} s", end="",
                  file=sys.stderr, flush=True)  # fmt: skip
        elif done % step == 0 or done == total:
            print(f"{done}/{total} robot-days done, {elapsed:.1f} s", file=sys.stderr,
                  flush=True)  # fmt: skip

    if args.what == "info":
        rows = run_on_dask(tasks, info_task, scheduler=args.scheduler, workers=args.workers,
                           progress=progress)  # fmt: skip
        columns = INFO_COLUMNS
    else:
        rows = run_on_dask(tasks, check_task, args.false_alarm, upkeep, scheduler=args.scheduler,
                           workers=args.workers, progress=progress)  # fmt: skip
        columns = CHECK_COLUMNS
    if tty:
        print(file=sys.stderr)
    if args.json:
        clean = [{k: _jsonable(v) for k, v in r.items()} for r in rows]
        print(json.dumps({"columns": table_columns(rows, columns), "rows": clean}))
        return _status(args, rows)
    out = args.table if args.table is not None else Path("/dev/stdout")
    try:
        write_table(rows, columns, out)
    except OSError as exc:
        raise CommandError(exc) from None
    if args.table is not None:
        print(f"{len(rows)} rows: {args.table}", file=sys.stderr)
    return _status(args, rows)


def _status(args: argparse.Namespace, rows: list[dict]) -> int:
    if args.what != "check":
        return 0
    found = any(r.get("changes") or r.get("proposals") not in (None, "", "-") for r in rows)
    return 1 if found else 0


def _jsonable(value):
    """numpy scalars as Python numbers; NaN (no value) as null."""
    value = value.item() if hasattr(value, "item") else value
    return None if isinstance(value, float) and not math.isfinite(value) else value
