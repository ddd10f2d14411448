"""argparse types shared by the commands and ``loopcal record``'s settings options."""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

_DURATION = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(s|m|min|h|d)?\s*$")
_UNIT_S = {None: 1.0, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0, "d": 86400.0}


def path_argument(text: str) -> Path:
    """A path from the command line; an empty one is refused (``Path("")`` would silently
    be the current directory)."""
    if text == "":
        raise argparse.ArgumentTypeError("an empty path")
    return Path(text)


def duration_argument(text: str) -> float:
    """A duration from the command line, in s: a number of seconds or a number with a
    unit, ``90``, ``90s``, ``15m``, ``2h``, ``1d``; more than 0 and finite."""
    m = _DURATION.match(text)
    if not m:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a duration (seconds, or a number with a unit: 90, 90s, 15m, 2h)")
    seconds = float(m.group(1)) * _UNIT_S[m.group(2)]
    if not (math.isfinite(seconds) and seconds > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: a duration must be more than 0")
    return seconds
