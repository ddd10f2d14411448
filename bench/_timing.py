"""Timing helpers shared by the bench scripts: medians over repeats, wall clock, and the
command line of a script that times something (``--repeats``)."""

from __future__ import annotations

import argparse
import statistics
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
