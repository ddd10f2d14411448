"""argparse types shared by the commands and ``loopcal record``'s settings options."""

from __future__ import annotations

import argparse
from pathlib import Path

from .times import parse_duration, parse_time


def path_argument(text: str) -> Path:
    """A path from the command line; an empty one is refused (``Path("")`` would silently
    be the current directory)."""
    if text == "":
        raise argparse.ArgumentTypeError("an empty path")
    return Path(text)


def duration_argument(text: str) -> float:
    """A duration from the command line, in s (:func:`loopcal.daemon.times.parse_duration`:
    ``90``, ``90s``, ``15m``, ``2h``, ``1d``; more than 0 and finite)."""
    try:
        return parse_duration(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def time_argument(text: str) -> int:
    """A time from the command line, ns since the Unix epoch
    (:func:`loopcal.daemon.times.parse_time`: what the commands print, or ISO 8601)."""
    try:
        return parse_time(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_recordings_argument(
    parser: argparse.ArgumentParser,
    *,
    optional: bool = False,
    help: str = "recording files or directories of them",  # noqa: A002 (argparse's name)
) -> None:
    """The positional ``recordings`` (``REC.mcap|DIR``, paths) every command that reads
    recordings takes: one or more, or any number with ``optional``."""
    parser.add_argument(
        "recordings", nargs="*" if optional else "+", type=path_argument,
        metavar="REC.mcap|DIR", help=help,
    )  # fmt: skip
