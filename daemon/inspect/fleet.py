"""A fleet's archives on Dask: ``loopcal info`` and ``loopcal check`` per robot and UTC day,
as tasks on a ``dask.distributed`` cluster, collected into one table.

A fleet root holds one directory per robot; each robot's directory holds its controller
config (``controller.toml``, or the name given) and its recordings (``loopcal-*.mcap``),
directly or in a ``recordings/`` directory below it::

    ROOT/robot-017/controller.toml
    ROOT/robot-017/recordings/loopcal-20261118T110640.000000Z.mcap ...

One task is one robot-day: the files whose names start on that UTC day (a day of a robot is
24 files of an hour; a task reads them one at a time, so a worker's memory is that of one
file). The scheduler sees only paths and small dicts: the recordings are read where the
workers run (a shared file system, or each robot's archive local to a worker). Loop closure
is tested per day: a change that goes on past midnight is found again on the next day.

Dask is an optional extra (``pip install loopcal[fleet]``): a robot's daemon never loads
this module.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .proposals import UpkeepSettings

CONFIG_NAME = "controller.toml"

#: the table's columns, in order (docs/fleet.md says what each holds)
INFO_COLUMNS = ("robot", "day", "files", "bytes", "scans", "start_utc", "end_utc",
                "scan_rate_hz", "missed", "gaps", "restarts", "events", "poses",
                "warnings", "damaged_files", "damaged_topics", "scans_lost",
                "damage")  # fmt: skip
#: damaged items a ``fleet info`` row's ``damage`` names (``loopcal info`` lists every one)
DAMAGE_ITEMS = 3
CHECK_COLUMNS = ("robot", "day", "files", "poses", "loops_close", "loops_open", "changes",
                 "sensors", "shifts_mm", "first_change_utc", "proposals",
                 "warnings")  # fmt: skip


class FleetError(ValueError):
    """A fleet root that cannot be read as one; the message names the directory."""


@dataclass(frozen=True)
class RobotDay:
    """One task: a robot's recordings of one UTC day, and its controller config."""

    robot: str
    day: str  # YYYY-MM-DD
    files: tuple[Path, ...]
    config: Path | None


def robots(root: Path, config_name: str = CONFIG_NAME) -> dict[str, tuple[list[Path], Path | None]]:
    """robot name -> (its recordings, oldest first; its controller config or None)."""
    from ..recording.names import find_recordings  # numpy: not for ``loopcal fleet --help``

    if not root.is_dir():
        raise FleetError(f"{root}: not a directory")
    out = {}
    for d in sorted(p for p in root.iterdir() if p.is_dir()):
        rec_dir = d / "recordings" if (d / "recordings").is_dir() else d
        files = find_recordings(rec_dir)
        if not files:
            continue
        config = d / config_name
        out[d.name] = (files, config if config.is_file() else None)
    if not out:
        raise FleetError(f"{root}: no robot directories with recordings (ROOT/ROBOT/*.mcap or "
                         "ROOT/ROBOT/recordings/*.mcap)")  # fmt: skip
    return out


def robot_days(root: Path, config_name: str = CONFIG_NAME) -> list[RobotDay]:
    """The fleet's tasks: every (robot, UTC day) with recordings, by robot then day."""
    from ..recording.names import name_time_ns

    tasks = []
    for robot, (files, config) in robots(root, config_name).items():
        days: dict[str, list[Path]] = {}
        for f in files:
            ns = name_time_ns(f)
            day = datetime.fromtimestamp(ns / 1e9, UTC).strftime("%Y-%m-%d") if ns else "?"
            days.setdefault(day, []).append(f)
        tasks += [RobotDay(robot, day, tuple(fs), config) for day, fs in sorted(days.items())]
    return tasks


# ---------------------------------------------------------------------------- the tasks
# (plain functions of plain data: Dask pickles them to the workers)


def info_task(task: RobotDay) -> dict[str, Any]:
    """One row of ``fleet info``: the summary of a robot-day."""
    from .summary import collect

    doc = collect(list(task.files)).as_json()
    return {
        "robot": task.robot, "day": task.day, "files": len(doc["files"]),
        "bytes": doc["bytes"], "scans": doc["scans"], "start_utc": doc["start_utc"],
        "end_utc": doc["end_utc"], "scan_rate_hz": doc["scan_rate_hz"],
        "missed": doc["missed"], "gaps": doc["gaps"], "restarts": doc["restarts"],
        "events": sum(doc["events"].values()), "poses": doc["poses"],
        "warnings": len(doc["warnings"]), **damage_columns(doc),
    }  # fmt: skip


def damage_columns(doc: dict[str, Any]) -> dict[str, Any]:
    """What of a robot-day was damaged, for its row: ``damaged_files`` (files with a damaged
    item or a reader's warning), ``damaged_topics`` (the topics of the damaged items,
    space-separated, sorted; "?" for an item no index names the topics of),
    ``scans_lost`` (scans known to be missing) and ``damage`` (the first
    :data:`DAMAGE_ITEMS` items, ``FILE: ITEM``, separated by `` | ``, with how many more)."""
    files = [f for f in doc["files"] if f.get("damage") or f.get("warning")]
    topics = set()
    for d in doc["damaged"]:
        topics |= set(d["topics"] or ["?"])
    items = [f"{Path(f['path']).name}: {text}" for f in files for text in f.get("damage", [])]
    items += [f["warning"] for f in files if f.get("warning") and not f.get("damage")]
    text = " | ".join(items[:DAMAGE_ITEMS])
    if len(items) > DAMAGE_ITEMS:
        text += f" | {len(items) - DAMAGE_ITEMS} more"
    return {"damaged_files": len(files), "damaged_topics": " ".join(sorted(topics)),
            "scans_lost": doc["scans_lost"], "damage": text}  # fmt: skip


def check_task(task: RobotDay, false_alarm: float,
               upkeep: UpkeepSettings | None = None) -> dict[str, Any]:  # fmt: skip
    """One row of ``fleet check``: loop closure of a robot-day at its controller config,
    and what the daemon's upkeep would propose from it (``upkeep``: its settings, None the
    daemon's defaults)."""
    from .loops import check, sensor_words
    from .proposals import proposal_column

    if task.config is None:
        return {"robot": task.robot, "day": task.day, "files": len(task.files), "poses": 0,
                "loops_close": None, "loops_open": None, "changes": 0, "sensors": "",
                "shifts_mm": "",
                "first_change_utc": "", "proposals": "", "warnings": 0,
                "error": "no controller config"}  # fmt: skip
    doc = check(list(task.files), task.config, false_alarm, upkeep=upkeep)
    changes = doc["changes"]
    return {
        "robot": task.robot, "day": task.day, "files": len(task.files), "poses": doc["poses"],
        "loops_close": doc["loops_close"], "loops_open": doc["loops_open"] is not None,
        "changes": len(changes),
        "sensors": " ".join(sensor_words(c).replace(" or ", "|") for c in changes),
        "shifts_mm": " ".join(f"{c['shift_mm']:+.3f}" for c in changes),
        "first_change_utc": changes[0]["start_utc"] if changes else "",
        "proposals": proposal_column(doc["proposals"]),
        "warnings": len(doc["warnings"]),
    }  # fmt: skip


# ---------------------------------------------------------------------------- on Dask


def run_on_dask(
    tasks: list[RobotDay],
    fn: Callable[..., dict[str, Any]],
    *args: Any,
    scheduler: str | None = None,
    workers: int = 2,
    progress: Callable[[int, int, float], None] | None = None,
) -> list[dict[str, Any]]:
    """``fn(task, *args)`` for every task on a Dask cluster; the rows in the tasks' order.

    scheduler: the address of a running scheduler (``tcp://host:8786``), or None for a local
    cluster of ``workers`` processes of one thread each (one robot-day at a time per
    worker: the work is numpy and file reading, and one thread per process keeps memory
    that of one file per worker). progress(done, total, elapsed_s) after each task.
    """
    from dask.distributed import Client, LocalCluster, as_completed

    t0 = time.perf_counter()
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=None)  # fmt: skip
    client = Client(cluster if cluster is not None else scheduler)
    try:
        futures = [client.submit(fn, t, *args, key=f"{fn.__name__}-{t.robot}-{t.day}",
                                 pure=False) for t in tasks]  # fmt: skip
        index = {f.key: i for i, f in enumerate(futures)}
        rows: list[dict[str, Any] | None] = [None] * len(futures)
        for done, f in enumerate(as_completed(futures), start=1):
            rows[index[f.key]] = f.result()
            if progress is not None:
                progress(done, len(futures), time.perf_counter() - t0)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return [r for r in rows if r is not None]


def table_columns(rows: list[dict[str, Any]], columns: tuple[str, ...]) -> list[str]:
    """The table's columns: ``columns``, then any other key of the rows, sorted."""
    return list(columns) + sorted({k for r in rows for k in r} - set(columns))


def write_table(rows: list[dict[str, Any]], columns: tuple[str, ...], path: Path) -> None:
    """The rows as CSV (``.csv``) or Parquet (``.parquet``, with pandas and pyarrow)."""
    cols = table_columns(rows, columns)
    if path.suffix == ".parquet":
        try:
            import pandas as pd
        except ImportError:
            raise FleetError(f"{path}: Parquet needs pandas and pyarrow; write .csv instead "
                             "or pip install pandas pyarrow") from None  # fmt: skip
        pd.DataFrame(rows, columns=cols).to_parquet(path, index=False)
        return
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=cols, restval="")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None or (isinstance(v, float) and math.isnan(v)) else v)
                        for k, v in r.items()})  # fmt: skip
