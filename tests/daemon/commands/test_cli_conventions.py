"""One convention for every ``loopcal`` command, checked by walking every command's parser
and help: every option has a help, no reST markup reaches ``--help``, ``--out`` is a
directory, the commands that report take ``--json``, ``--free`` takes one syntax, errors
read ``loopcal CMD: error: ...`` with exit status 2, docs/daemon.md's table of keys is
the settings' own, and its example config holds their defaults."""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from loopcal.daemon.arguments import duration_argument
from loopcal.daemon.cli import build_parser
from loopcal.daemon.commands import COMMANDS
from loopcal.daemon.recorder.settings import (
    DEFAULTS,
    SETTINGS,
    load_daemon_config,
    markdown_table,
)
from tests.support import ROOT
from tests.support.processes import loopcal_main

NAMES = [name for name, _ in COMMANDS]
#: the commands that report something a program may want to read
REPORTING = {"calibrate", "info", "check", "fleet", "compact", "observability", "record",
             "files", "demo"}  # fmt: skip
REST = re.compile(r"``|:(mod|func|class|data|meth|attr|exc|obj):`")


def _command_parser(name: str) -> argparse.ArgumentParser:
    parser = build_parser(name)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def _options(p: argparse.ArgumentParser) -> list[argparse.Action]:
    return [a for a in p._actions if not isinstance(a, argparse._HelpAction)]


@pytest.mark.parametrize("name", NAMES)
def test_every_argument_has_a_help(name: str) -> None:
    missing = [a.option_strings or a.dest for a in _options(_command_parser(name))
               if not a.help or a.help == argparse.SUPPRESS]  # fmt: skip
    assert not missing, f"loopcal {name}: no help for {missing}"


@pytest.mark.parametrize("name", [None, *NAMES])
def test_help_is_plain_text(name: str | None) -> None:
    text = (_command_parser(name) if name else build_parser()).format_help()
    assert not REST.search(text), f"reST markup in loopcal {name or ''} --help: " \
        f"{REST.search(text).group(0)!r}"  # fmt: skip


@pytest.mark.parametrize("name", NAMES)
def test_out_is_a_directory(name: str) -> None:
    for a in _options(_command_parser(name)):
        if "--out" in a.option_strings:
            assert a.metavar == "DIR", f"loopcal {name} --out is {a.metavar}, not a DIR"


@pytest.mark.parametrize("name", NAMES)
def test_every_duration_takes_the_one_spelling(name: str) -> None:
    """A duration (metavar D, and every --duration) is seconds or a number with a unit,
    the same spelling in every command: 1.5m is 90 s, and 0 is refused."""
    for a in _options(_command_parser(name)):
        if ("--duration" in a.option_strings or "--last" in a.option_strings
                or a.type is duration_argument):  # fmt: skip
            assert a.metavar == "D", f"loopcal {name} {a.option_strings[0]} is {a.metavar}"
        if a.metavar != "D":
            continue
        value = a.type("1.5m")
        seconds = value.total_seconds() if hasattr(value, "total_seconds") else value
        assert seconds == 90.0, (name, a.option_strings, value)
        with pytest.raises(argparse.ArgumentTypeError, match="more than 0"):
            a.type("0")


@pytest.mark.parametrize("name", sorted(REPORTING))
def test_reporting_commands_take_json(name: str) -> None:
    flags = {s for a in _options(_command_parser(name)) for s in a.option_strings}
    assert "--json" in flags, f"loopcal {name} has no --json"


def test_the_readme_names_the_commands_without_json() -> None:
    """The README's one sentence on --json names exactly the commands that lack it."""
    text = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    m = re.search(r"every command takes `--json` .*? but these: (.*?); exit", text)
    assert m, "the README's sentence on --json is gone"
    named = set(re.findall(r"`([a-z-]+)`", m.group(1)))
    flags = {n: {s for a in _options(_command_parser(n)) for s in a.option_strings} for n in NAMES}
    without = {n for n in NAMES if "--json" not in flags[n]}
    assert named == without


def test_a_command_option_before_the_command_is_named_as_such() -> None:
    refused = loopcal_main("--json", "info", "x.mcap")
    assert refused.returncode == 2
    assert refused.stderr.endswith(
        "loopcal: error: --json is not an option of loopcal itself: put it after the command "
        "(loopcal info --json ...)\n"
    )
    assert "loopcal info: error" not in refused.stderr


@pytest.mark.parametrize("name", ["calibrate", "demo", "observability"])
def test_free_takes_one_value_in_one_syntax(name: str) -> None:
    p = _command_parser(name)
    (free,) = [a for a in _options(p) if "--free" in a.option_strings]
    assert free.nargs is None, f"loopcal {name} --free takes nargs={free.nargs!r}"
    assert "d01,d02,A1x" in free.help


def test_free_does_not_swallow_the_recordings() -> None:
    args = _command_parser("calibrate").parse_args(["--free", "d03", "REC.mcap"])
    assert args.free == "d03" and args.recordings == [Path("REC.mcap")]


_loopcal = loopcal_main  # the parser's and the commands' answers: no process needed


@pytest.mark.slow
@pytest.mark.parametrize("argv", [["record", "--daq", "nope://x", "--out", "/tmp/x"],
                                  ["calibrate", "--no-such-option"]])  # fmt: skip
def test_a_refusal_is_exit_2_and_one_line_from_a_real_process_too(argv: list[str]) -> None:
    """What the shell sees: status 2, the one line, no traceback (the rest of this module
    asks cli.main in this process)."""
    proc = subprocess.run([sys.executable, "-m", "loopcal.daemon.cli", *argv],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert [ln for ln in proc.stderr.splitlines() if "error:" in ln] == [
        ln for ln in proc.stderr.splitlines() if ln.startswith(f"loopcal {argv[0]}: error: ")]
    assert "Traceback" not in proc.stderr and proc.stdout == ""


@pytest.mark.parametrize("name", NAMES)
def test_a_bad_option_is_exit_2_naming_the_command(name: str) -> None:
    proc = _loopcal(name, "--no-such-option")
    assert proc.returncode == 2
    assert f"loopcal {name}: error: " in proc.stderr, proc.stderr


@pytest.mark.parametrize("argv", [
    ["info", "/nonexistent/x.mcap"],
    ["check", "/nonexistent/x.mcap", "--controller-config", "/nonexistent/c.toml"],
    ["calibrate", "/nonexistent/x.mcap", "--controller-config", "/nonexistent/c.toml"],
    ["compact", "/nonexistent/x.mcap"],
    ["replay", "/nonexistent/x.mcap"],
    ["observability", "--free", "Q9"],
    ["observability", "--session", "60", "--twist-every", "-1"],
    ["demo", "--free", "Q9"],
    ["files", "nope"],
    ["install-units", "/nonexistent"],
    ["init-config", "/nonexistent/dir/c.toml"],
    ["daemon", "--config", "/nonexistent/d.toml"],
    ["record", "--daq", "nope://x", "--out", "/tmp/x"],
])  # fmt: skip
def test_bad_input_is_exit_2_with_one_error_line(argv: list[str]) -> None:
    proc = _loopcal(*argv)
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert f"loopcal {argv[0]}: error: " in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr


def test_the_docs_table_of_keys_is_the_settings_own() -> None:
    assert markdown_table() in (ROOT / "docs" / "daemon.md").read_text()


def test_the_docs_example_config_holds_the_settings_defaults(tmp_path: Path) -> None:
    """docs/daemon.md's example config is a config the daemon takes, and each of its
    values is the setting's default, but for those whose line says why not (a comment: a
    required key, or an example of a value to choose)."""
    text = (ROOT / "docs" / "daemon.md").read_text()
    block = re.search(r"^## The config file\n.*?^```toml\n(.*?)^```", text, re.M | re.S)
    assert block, "docs/daemon.md: no ```toml block under '## The config file'"
    example = tmp_path / "daemon.toml"
    example.write_text(block.group(1))
    settings = load_daemon_config(example)  # every key known, every value taken
    table = ""
    checked = []
    for line in block.group(1).splitlines():
        if m := re.match(r"^\[(\w+)\]\s*$", line):
            table = m.group(1)
        elif m := re.match(r"^(\w+)\s*=\s*(.*?)\s*(#.*)?$", line):
            key, why = f"[{table}].{m.group(1)}", m.group(3)
            (name,) = [n for n, spec in SETTINGS.items() if spec.key == key]
            if why is None:
                assert name in DEFAULTS, f"{key} has no default: say why in a comment"
                assert getattr(settings, name) == DEFAULTS[name], \
                    (f"docs/daemon.md's example sets {key} = {m.group(2)}, the default is "
                     f"{DEFAULTS[name]!r}: change it, or say why in a comment")  # fmt: skip
                checked.append(key)
    assert len(checked) >= 8, checked


@pytest.mark.parametrize("command", ["info", "check", "compact", "calibrate"])
def test_what_is_not_a_regular_file_is_refused_at_once(command: str, tmp_path: Path) -> None:
    """A device never ends (/dev/zero), a FIFO blocks its reader, an empty path would be
    the current directory: each is bad input, refused before anything is read."""
    fifo = tmp_path / "x.mcap"
    os.mkfifo(fifo)
    config = tmp_path / "controller.toml"
    assert _loopcal("init-config", str(config)).returncode == 0
    extra = [] if command in ("info", "compact") else ["--controller-config", str(config)]
    for target, words in (("/dev/zero", "not a regular file (a character device)"),
                          (str(fifo), "not a regular file (a FIFO)"),
                          ("", "an empty path")):  # fmt: skip
        proc = _loopcal(command, target, *extra)
        assert proc.returncode == 2, (target, proc.stderr)
        assert f"loopcal {command}: error: " in proc.stderr and words in proc.stderr, proc.stderr
        assert "Traceback" not in proc.stderr


def test_observability_json_says_what_its_text_says_and_exits_1_when_unobservable() -> None:
    import json

    ok = _loopcal("observability", "--json", "--poses", "200")
    assert ok.returncode == 0, ok.stderr
    doc = json.loads(ok.stdout)
    assert doc["observable"] is True and set(doc["status"]) == set(doc["free"])
    assert doc["poses"] == 200 and all(v == "ok" for v in doc["status"].values())
    text = _loopcal("observability", "--poses", "200").stdout
    for name, status in doc["status"].items():
        assert re.search(rf"^\s*{name}: {status}\b", text, re.M), (name, text)
    every = _loopcal("observability", "--json", "--free", "all", "--poses", "200")
    assert every.returncode == 1, every.stderr  # k1, k2 cannot be told from the offsets
    doc = json.loads(every.stdout)
    assert doc["observable"] is False and doc["weak_directions"]
    assert "unobservable" in doc["status"].values() and doc["suggested_free"]


def test_observability_of_a_session_follows_how_the_technician_moves() -> None:
    """--twist-every changes the simulated session whose scans are judged: the same seed
    moved with and without twists gives different information (and both are observable)."""
    import json

    docs = [json.loads(_loopcal("observability", "--json", "--session", "60",
                                "--twist-every", n).stdout) for n in ("0", "2")]  # fmt: skip
    assert all(d["observable"] and d["poses"] == 1200 for d in docs)
    assert docs[0]["indices"] != docs[1]["indices"]
