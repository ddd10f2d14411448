"""How loopcal spells a time and a duration: in every command's output, ``--json``
document and option.

A time is ISO 8601 in UTC to the millisecond, with a ``Z``: ``2026-12-03T08:37:37.357Z``
(truncated, never rounded up into the next millisecond). Every time option takes that
spelling, any other ISO 8601 time (an offset such as ``+01:00``; no offset means UTC; a
space for the ``T``; a date alone is its midnight) and the ``... UTC`` suffix older
versions printed. A duration is a number of seconds or a number with a unit: ``90``,
``90s``, ``15m``, ``2h``, ``1d``.

Names of files carry times too, in ISO 8601's basic format without the colons a file name
cannot always hold: :func:`name_stamp` (``20261203T083737Z``: a kept config, a discarded
proposal, a session) and the recordings' own names (to the microsecond, so that they sort:
:mod:`loopcal.daemon.recording.names`).
"""

from __future__ import annotations

import math
import re
import time
from datetime import UTC, datetime

NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000

_DURATION = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(s|m|min|h|d)?\s*$")
_UNIT_S = {None: 1.0, "s": 1.0, "m": 60.0, "min": 60.0, "h": 3600.0, "d": 86400.0}
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)


def time_text(ns: int) -> str:
    """A time for people and documents alike.

    Parameters
    ----------
    ns : int
        ns since the Unix epoch (UTC).

    Returns
    -------
    str
        ``2026-12-03T08:37:37.357Z``; ``"N ns"`` for a time a datetime cannot hold (a
        damaged file's stamp), so that the number is still shown rather than lost.
    """
    sec, rest = divmod(int(ns), NS_PER_S)
    try:
        t = datetime.fromtimestamp(sec, UTC)
    except (OverflowError, OSError, ValueError):
        return f"{ns} ns"
    return f"{t:%Y-%m-%dT%H:%M:%S}.{rest // NS_PER_MS:03d}Z"


def now_text() -> str:
    """The time now, in :func:`time_text`'s spelling (what a config or report was written)."""
    return time_text(time.time_ns())


def name_stamp(ns: int | None = None) -> str:
    """A time for a file's name: ``20261203T083737Z`` (to the second), now by default."""
    t = datetime.fromtimestamp((time.time_ns() if ns is None else ns) // NS_PER_S, UTC)
    return f"{t:%Y%m%dT%H%M%SZ}"


def time_or(ns: int | None, missing: str = "?") -> str:
    """:func:`time_text`, or ``missing`` for an unknown time (text output)."""
    return missing if ns is None else time_text(ns)


def time_json(ns: int | None) -> str | None:
    """:func:`time_text` for a ``--json`` document: an unknown time stays null."""
    return None if ns is None else time_text(ns)


def span_text(start_ns: int | None, end_ns: int | None) -> str:
    """A time span: ``<start> to <end>`` in :func:`time_text`'s spelling; ``""`` when
    either end is unknown."""
    if start_ns is None or end_ns is None:
        return ""
    return f"{time_text(start_ns)} to {time_text(end_ns)}"


def parse_time(text: str) -> int:
    """A time as an option or a file gives it.

    Parameters
    ----------
    text : str
        :func:`time_text`'s spelling, any ISO 8601 time (no offset: UTC) or the same
        followed by `` UTC``.

    Returns
    -------
    int
        ns since the Unix epoch (to the microsecond a datetime holds).

    Raises
    ------
    ValueError
        Naming the text and the spellings taken.
    """
    s = text.strip()
    if s.endswith(" UTC"):
        s = s[: -len(" UTC")]
    try:
        t = datetime.fromisoformat(s)
    except ValueError:
        raise ValueError(f"{text!r} is not a time (ISO 8601, as loopcal prints times: "
                         "2026-12-03T08:37:37.357Z, or 2026-12-03T09:37+01:00)") from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    delta = t - _EPOCH
    return (delta.days * 86_400 + delta.seconds) * NS_PER_S + delta.microseconds * 1000


def parse_duration(text: str) -> float:
    """A duration as an option gives it, in s.

    Parameters
    ----------
    text : str
        A number of seconds or a number with a unit: ``90``, ``90s``, ``15m``, ``15min``,
        ``2h``, ``1d``.

    Returns
    -------
    float
        Seconds, more than 0 and finite.

    Raises
    ------
    ValueError
        Naming the text and the spellings taken.
    """
    m = _DURATION.match(text)
    if not m:
        raise ValueError(
            f"{text!r} is not a duration (seconds, or a number with a unit: 90, 90s, 15m, 2h)")
    seconds = float(m.group(1)) * _UNIT_S[m.group(2)]
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"{text!r}: a duration must be more than 0")
    return seconds


__all__ = ["name_stamp", "now_text", "parse_duration", "parse_time", "span_text", "time_json",
           "time_or", "time_text"]  # fmt: skip
