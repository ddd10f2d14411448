"""``loopcal init-config PATH [--force]``: write a controller config (TOML) with the 20
parameters at the reference geometry, each with a comment saying what it is and its unit.

The file is written atomically and never over an existing one unless ``--force``; its parent
directory must exist. Exit status 0 when written, 2 when not (the reason on stderr)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .errors import run_command


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("path", help="where to write it, e.g. /etc/loopcal/controller/controller.toml")
    p.add_argument("--force", action="store_true", help="overwrite an existing file")


def run(args: argparse.Namespace) -> int:
    from ..config.controller import write_initial_config

    path = write_initial_config(args.path, force=args.force)
    where = str(path)
    if path != Path(args.path):
        where += f" (through the symlink {args.path}, which stays a link)"
    print(
        f"wrote {where}: the 20 parameters at the reference geometry "
        "(edit the gains S1..S4 to your bench values)"
    )
    return 0


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(
        prog="loopcal init-config",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(_parser)
    sys.exit(run_command("init-config", run, _parser.parse_args()))
