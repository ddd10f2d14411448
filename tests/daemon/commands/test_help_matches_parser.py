"""Every command's ``--help`` against what its parser and its run do (issue 32): every option
the help names is the command's own (or named with the command or program it belongs to),
an option whose help says "with --X:" is refused without X (and "not with --X:" with it),
exit status 2 naming both, and a default the help prints is the parser's."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from loopcal.daemon.cli import build_parser
from loopcal.daemon.commands import COMMANDS
from tests.support.processes import loopcal, loopcal_main
from tests.support.recordings import write_recording
from tests.support.rows import make_rows

NAMES = [name for name, _ in COMMANDS]
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
#: other programs' options a help names, and the program written before each
FOREIGN = {"--create": "systemd-tmpfiles"}
#: "with --X:", "with --X VALUE:", "not with --X:" opening an option's help
RULE = re.compile(r"^(not )?with (--[a-z][\w-]*)(?: ([\w.-]+))?: ")
#: the printed default: "(default 50)", "(default: paper7)", "(default 1e-08, the daemon's)"
DEFAULT = re.compile(r"\(default:? (.*?)(?:\)|;|, )")
#: commands that serve until stopped if an option were not refused: asked in a process of
#: their own (``simulate`` stops after --duration; the timeout only ends a test that hangs)
SERVES = {"simulate", "replay", "demo", "daemon"}


def _required(name: str, tmp: Path) -> list[str]:
    """What command ``name`` needs besides the option tested: what it is given before its
    options are checked, a bounded run for a server."""
    if name == "record":
        return ["--daq", "nope://x", "--out", str(tmp / "out")]
    if name == "replay":  # a real recording: the file is read before the options
        path = tmp / "x.mcap"
        write_recording(path, make_rows(40))
        return [str(path)]
    if name == "simulate":
        return ["--duration", "0.5"]
    return []


def _parser(name: str) -> argparse.ArgumentParser:
    parser = build_parser(name)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _options(name: str) -> dict[str, argparse.Action]:
    return dict(_parser(name)._option_string_actions)


def _mentions() -> Iterator:
    for name in NAMES:
        text = _parser(name).format_help()
        for m in OPTION.finditer(text):
            yield pytest.param(name, m.group(0), text[max(0, m.start() - 60):m.start()],
                               id=f"{name} {m.group(0)}")  # fmt: skip


def _unique(params: Iterator) -> list:
    seen, out = set(), []
    for p in params:
        if p.id not in seen:
            seen.add(p.id)
            out.append(p)
    return out


@pytest.mark.parametrize(("name", "option", "before"), _unique(_mentions()))
def test_every_option_the_help_names_is_taken(name: str, option: str, before: str) -> None:
    """An option in the help (usage, description, any option's help) is the command's, or
    comes right after the command (``loopcal calibrate --write``) or program it belongs to."""
    if option in _options(name):
        return
    if (program := FOREIGN.get(option)) is not None:
        assert before.endswith(f"{program} "), (name, option, before)
        return
    other = re.search(r"loopcal ([a-z-]+) $", before)
    assert other and other[1] in NAMES, \
        f"loopcal {name} --help names {option}, which it does not take: ...{before}{option}"
    assert option in _options(other[1]), f"loopcal {other[1]} takes no {option}"


def _cli_value(action: argparse.Action) -> str:
    """A value the option takes: its default as the command line writes it (not 0, which
    may mean "none": 1 or 0.5), else the default its help prints, else 10."""
    d = action.default
    if d == 0 and not isinstance(d, bool):
        return "1" if isinstance(d, int) else "0.5"
    if isinstance(d, tuple):
        return ",".join(f"{v:g}" for v in d)
    if isinstance(d, float):
        return f"{d:g}"
    if d is not None and not isinstance(d, bool):
        return str(d)
    m = DEFAULT.search(action.help or "")
    return re.split(r"[\s:]", m[1])[0] if m else "10"


def _rules() -> Iterator:
    for name in NAMES:
        for option, action in _options(name).items():
            m = RULE.match(action.help or "")
            if m and option == max(action.option_strings, key=len):
                slow = [pytest.mark.slow] if name in SERVES else []
                yield pytest.param(name, option, bool(m[1]), m[2], m[3], id=f"{name} {option}",
                                   marks=slow)  # fmt: skip


@pytest.mark.parametrize(("name", "option", "negated", "needs", "value"), list(_rules()))
def test_an_option_only_with_another_is_refused_without_it(name: str, option: str, negated: bool,
                                                           needs: str, value: str | None,
                                                           tmp_path: Path) -> None:  # fmt: skip
    """``--select`` ("with --method paper: ...") without ``--method paper``, ``--poses``
    ("not with --session: ...") with ``--session``: exit status 2, the error naming both,
    before anything runs."""
    opts = _options(name)
    argv = [name, option, _cli_value(opts[option])]
    other = opts[needs]
    if negated:
        argv += [needs, _cli_value(other)] if other.nargs != 0 else [needs]
    elif value is not None and other.default == value:  # the default meets it: another value
        choices = [c for c in other.choices or () if c != value]
        if not choices:
            pytest.skip(f"{needs} takes no other value to refuse {option} with")
        argv += [needs, choices[0]]
    argv += _required(name, tmp_path)
    if name in SERVES:
        pytest.importorskip("pymodbus")
        proc = loopcal(*argv, timeout=120)
    else:
        proc = loopcal_main(*argv)
    assert proc.returncode == 2, (argv, proc.stdout[-500:], proc.stderr[-500:])
    errors = [ln for ln in proc.stderr.splitlines() if ln.startswith(f"loopcal {name}: error: ")]
    assert errors and option in errors[0] and needs in errors[0], (argv, proc.stderr)


def _defaults() -> Iterator:
    for name in NAMES:
        for option, action in _options(name).items():
            m = DEFAULT.search(action.help or "")
            if m and option == max(action.option_strings, key=len):
                yield pytest.param(name, option, m[1], id=f"{name} {option}")


@pytest.mark.parametrize(("name", "option", "printed"), list(_defaults()))
def test_the_default_the_help_prints_is_the_parsers(name: str, option: str, printed: str) -> None:
    """"(default 50)" in ``--select``'s help is the 50 the parser gives without it, read
    through the option's own type ("256 MiB", "0.8,1.5", "75 s"). A default in words ("a
    free one", "the controller config's [calibration].free") and one the parser leaves to
    the run (None: it depends on other options, or tells whether the option was given)
    cannot be compared here."""
    action = _options(name)[option]
    if action.default is None or isinstance(action.default, bool):
        return
    convert = action.type if callable(action.type) else str
    for text in (printed, re.split(r"[\s:]", printed)[0]):
        try:
            value = convert(text)
        except (ValueError, TypeError, argparse.ArgumentTypeError):
            continue
        assert value == action.default, \
            f"loopcal {name} {option}: help says default {printed!r}, the parser's is " \
            f"{action.default!r}"  # fmt: skip
        return
    assert not re.match(r"^[-+.\d]", printed), \
        f"loopcal {name} {option}: help's default {printed!r} is not a value of the option"
