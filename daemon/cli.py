"""The ``loopcal`` command line: parses the arguments and dispatches to the command's module
in :mod:`loopcal.daemon.commands`, importing only that one (``loopcal --help`` imports none)."""

from __future__ import annotations

import argparse
import re
import sys

from .commands import COMMANDS, load
from .commands.errors import run_command
from .version import loopcal_version

#: the docs the help texts name (docs/daemon.md, ...) are installed with loopcal
DOCS_EPILOG = "docs/*.md, systemd/*: installed with loopcal; `loopcal files` says where."

#: the options of ``loopcal`` itself, before the command; a command's options follow it
_GLOBAL_OPTIONS = frozenset({"-h", "--help", "--version"})

#: a reST cross-reference, :role:`target`, :role:`~a.b.target` or :role:`text <target>`
_ROLE = re.compile(r":[a-z]+:`(~?)([^`<]*?)\s*(?:<[^>]*>)?`")


def plain_text(doc: str) -> str:
    """A docstring (reST, for the API reference) as ``--help`` shows it: ``x`` as x, a
    cross-reference :mod:`a.b` as a.b, :mod:`~a.b` as b."""
    text = _ROLE.sub(lambda m: m.group(2).rsplit(".", 1)[-1] if m.group(1) else m.group(2), doc)
    return text.replace("``", "")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser: every command listed with its one-line help; the arguments of
    ``command`` only (its module is imported), if given."""
    parser = argparse.ArgumentParser(
        prog="loopcal",
        description="Closed-loop field calibration of the redundant shoulder joint.",
        epilog=DOCS_EPILOG,
    )
    parser.add_argument("--version", action="version", version=f"loopcal {loopcal_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, help_text in COMMANDS:
        if name != command:
            sub.add_parser(name, help=help_text, add_help=False)
            continue
        module = load(name)
        description = getattr(module, "DESCRIPTION", None) or module.__doc__ or ""
        p = sub.add_parser(
            name,
            help=help_text,
            description=plain_text(description),
            formatter_class=argparse.RawDescriptionHelpFormatter,
            epilog=DOCS_EPILOG,
        )
        module.add_arguments(p)
        p.set_defaults(func=module.run, parser=p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``loopcal`` with ``argv`` (default: the process's arguments); the exit status.

    A command's refusal (:class:`~loopcal.daemon.commands.errors.CommandError`, or a domain
    error that means bad input) is printed here, ``loopcal CMD: error: MESSAGE`` one line per
    line of its message, and its status returned; anything else raised is a bug and is
    raised on (a traceback, exit status 1).
    """
    argv = sys.argv[1:] if argv is None else list(argv)
    # the command is the first word that is not an option (loopcal has no global option
    # that takes a value)
    names = {name for name, _ in COMMANDS}
    at = next((i for i, a in enumerate(argv) if not a.startswith("-")), len(argv))
    command = argv[at] if at < len(argv) else None
    parser = build_parser(command if command in names else None)
    before = [a for a in argv[:at] if a not in _GLOBAL_OPTIONS]
    if before and command in names:
        parser.error(f"{before[0]} is not an option of loopcal itself: put it after the "
                     f"command (loopcal {command} {' '.join(before)} ...)")  # fmt: skip
    args, extra = parser.parse_known_args(argv)
    if extra:  # said by the command's parser: "loopcal CMD: error: ...", exit 2
        args.parser.error(f"unrecognized arguments: {' '.join(extra)}")
    return run_command(args.command, args.func, args)


if __name__ == "__main__":
    sys.exit(main())
