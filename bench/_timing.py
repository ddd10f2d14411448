"""Timing helpers shared by the bench scripts: medians over repeats, wall clock (of a call,
or of commands in fresh processes), and the command line of a script that times something
(``--repeats``)."""

from __future__ import annotations

import argparse
import statistics
import subprocess
import time
from collections.abc import Callable
from typing import Any


def median_time(fn: Callable[[], Any], repeats: int = 5) -> tuple[float, Any]:
    """Median wall time of ``fn()`` over ``repeats`` runs, in seconds, and its last result."""
    times = []
    result = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), result


def wall(cmd: list[str], ok: tuple[int, ...] = (0,)) -> float:
    """Wall time of one run of ``cmd`` in a fresh process, s; exits naming it (and its
    stderr) if its exit status is not one of ``ok``."""
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    took = time.perf_counter() - t
    if proc.returncode not in ok:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr}")
    return took


def interleaved_medians(cases: dict[str, list[str]], repeats: int,
                        ok: tuple[int, ...] = (0,)) -> dict[str, float]:  # fmt: skip
    """Median wall time of each command of ``cases`` (name -> argv), s, over ``repeats``
    fresh processes each: one run of each first (the page cache warmed), then the runs of
    all interleaved, so that a busy machine slows them alike (:func:`wall`)."""
    for cmd in cases.values():
        wall(cmd, ok)
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeats):
        for name, cmd in cases.items():
            times[name].append(wall(cmd, ok))
    return {name: statistics.median(ts) for name, ts in times.items()}


def repeats_parser(doc: str, default: int = 5) -> argparse.ArgumentParser:
    """The command line of a bench script that times something: its docstring's first
    paragraph as the description, and ``--repeats`` (runs per timing, :func:`median_time`).

    Parameters
    ----------
    doc : str
        The script's docstring.
    default : int
        Repeats when ``--repeats`` is not given.

    Returns
    -------
    argparse.ArgumentParser
        The parser, for the script to add its own options to.
    """
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument(
        "--repeats", type=int, default=default, help=f"runs per timing, the median kept ({default})"
    )
    return ap
