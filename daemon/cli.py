"""The ``loopcal`` command line: parses the arguments and dispatches to the command's module
in :mod:`daemon.commands`."""

from __future__ import annotations

import argparse
import sys
from types import ModuleType

from calibration.errors import CalibrationError

from .commands import (
    calibrate,
    daemon,
    demo,
    init_config,
    observability,
    record,
    replay,
    simulate,
)

#: (name, module) in the order ``loopcal --help`` lists them
COMMANDS: list[tuple[str, ModuleType]] = [
    ("demo", demo),
    ("record", record),
    ("daemon", daemon),
    ("init-config", init_config),
    ("calibrate", calibrate),
    ("replay", replay),
    ("simulate", simulate),
    ("observability", observability),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="loopcal",
        description="Closed-loop field calibration of the redundant shoulder joint.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name, module in COMMANDS:
        p = sub.add_parser(
            name,
            help=module.HELP,
            description=getattr(module, "DESCRIPTION", None) or module.__doc__,
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        module.add_arguments(p)
        p.set_defaults(func=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (CalibrationError, ValueError) as exc:
        print(f"loopcal: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
