"""The live guidance on a terminal, for the commands that guide a technician: ``loopcal
record --until-enough`` (its own guidance) and ``loopcal session`` (the daemon's)."""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import TYPE_CHECKING

from ..live.guidance_defaults import MAX_TARGET_MM, TARGET_MM

if TYPE_CHECKING:  # the guidance (numpy, the worker) is loaded by the command that runs it
    from ..live.guidance import GuidanceUpdate


def target_mm_argument(text: str) -> float:
    """The type of ``--target-mm``: mm, above 0 and at most :data:`MAX_TARGET_MM`."""
    try:
        mm = float(text)
    except ValueError:
        mm = math.nan
    if not (math.isfinite(mm) and 0 < mm <= MAX_TARGET_MM):
        raise argparse.ArgumentTypeError(
            f"{text!r}: a target must be more than 0 and at most {MAX_TARGET_MM:g} mm"
        )
    return mm


def add_guidance_options(p: argparse.ArgumentParser, *, until_enough: str,
                         target_with: str = "") -> None:  # fmt: skip
    """``--until-enough`` (its help ``until_enough``) and ``--target-mm`` (default None:
    :data:`TARGET_MM`; its help begins with ``target_with``), as ``loopcal record`` and
    ``loopcal session`` take them."""
    p.add_argument("--until-enough", action="store_true", help=until_enough)
    p.add_argument("--target-mm", type=target_mm_argument, default=None, metavar="MM",
                   help=f"{target_with}every offset's standard deviation the guidance aims "
                        f"for (default {TARGET_MM:g}, at most {MAX_TARGET_MM:g})")  # fmt: skip


def target_mm(args: argparse.Namespace) -> float:
    """The target ``--target-mm`` chose: its value, or :data:`TARGET_MM` when it was not
    given (its default None tells the two apart)."""
    return TARGET_MM if args.target_mm is None else args.target_mm


class Display:
    """The live guidance on stdout: redrawn in place on a terminal (plain ANSI, fine over
    SSH), a block per update otherwise, or one JSON object per line."""

    def __init__(self, *, json_lines: bool) -> None:
        self.json_lines = json_lines
        self.tty = sys.stdout.isatty()
        self._lines = 0

    def update(self, u: GuidanceUpdate) -> None:
        if self.json_lines:
            print(json.dumps(u.as_json()), flush=True)
            return
        self.lines(u.render())

    def lines(self, lines: list[str]) -> None:
        """Show ``lines`` in place of the previous display."""
        if self.tty:
            # back to the top of the previous display, clear it, draw again
            up = f"\x1b[{self._lines}F" if self._lines else ""
            sys.stdout.write(up + "\x1b[J" + "\n".join(lines) + "\n")
            sys.stdout.flush()
            self._lines = len(lines)
        else:
            print("\n".join(lines) + "\n", flush=True)
