"""The live guidance on a terminal, for the commands that guide a technician: ``loopcal
record --until-enough`` (its own guidance) and ``loopcal session`` (the daemon's)."""

from __future__ import annotations

import json
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the guidance (numpy, the worker) is loaded by the command that runs it
    from ..live.guidance import GuidanceUpdate


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
