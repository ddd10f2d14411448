"""argparse types shared by the commands and ``loopcal record``'s settings options."""

from __future__ import annotations

import argparse
from pathlib import Path


def path_argument(text: str) -> Path:
    """A path from the command line; an empty one is refused (``Path("")`` would silently
    be the current directory)."""
    if text == "":
        raise argparse.ArgumentTypeError("an empty path")
    return Path(text)
