"""One error path for every command: a refusal, raised as ``CommandError`` or as a domain
error that means bad input, is ``loopcal CMD: error: ...`` on stderr and its exit status,
printed by ``cli.main`` alone (through ``run_command``); anything else raised is a bug and
stays a traceback, exit status 1, never "bad input"."""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from loopcal.calibration.errors import CalibrationError, ParameterError
from loopcal.daemon.cli import main
from loopcal.daemon.commands.errors import (
    BAD_INPUT,
    CommandError,
    as_refusal,
    resolve_name,
    run_command,
)
from loopcal.daemon.config.controller import ControllerConfigError
from loopcal.daemon.recorder.settings import SettingsError
from loopcal.daemon.recording import RecordingError

ARGS = argparse.Namespace()


def _raising(exc: BaseException):
    def run(args: argparse.Namespace) -> int:
        raise exc

    return run


def test_a_refusal_is_one_line_and_exit_2(capsys) -> None:
    assert run_command("demo", _raising(CommandError("--speed 0: must be positive")), ARGS) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == "loopcal demo: error: --speed 0: must be positive\n"


def test_a_refusal_says_its_own_status_one_line_per_problem(capsys) -> None:
    refusal = CommandError("a.conf differs from loopcal's\nb.conf differs from loopcal's", 1)
    assert run_command("install-units", _raising(refusal), ARGS) == 1
    assert capsys.readouterr().err.splitlines() == [
        "loopcal install-units: error: a.conf differs from loopcal's",
        "loopcal install-units: error: b.conf differs from loopcal's",
    ]


@pytest.mark.parametrize("exc", [
    RecordingError("x.mcap: not an MCAP file"),
    ControllerConfigError("c.toml: A1x = 1e+300 is not plausible"),
    SettingsError("[daq].url: no host"),
    ParameterError("unknown parameter 'Q9'"),
    CalibrationError("too few poses"),
])  # fmt: skip
def test_a_domain_error_that_means_bad_input_is_a_refusal(exc: Exception, capsys) -> None:
    assert run_command("calibrate", _raising(exc), ARGS) == 2
    assert capsys.readouterr().err == f"loopcal calibrate: error: {exc}\n"


@pytest.mark.parametrize("exc", [ValueError("a bug"), TypeError("a bug"), KeyError("a bug"),
                                 ZeroDivisionError("a bug"), OSError("a bug")])  # fmt: skip
def test_a_programming_error_is_raised_on_not_called_bad_input(exc: Exception, capsys) -> None:
    with pytest.raises(type(exc)):
        run_command("calibrate", _raising(exc), ARGS)
    assert capsys.readouterr().err == ""
    assert as_refusal(exc) is None


def test_a_programming_error_is_pythons_traceback_and_exit_1() -> None:
    program = ("import sys\nfrom loopcal.daemon.commands.errors import run_command\n"
               "def run(args):\n    raise ValueError('a bug')\n"
               "sys.exit(run_command('demo', run, None))\n")  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    assert proc.returncode == 1, proc.stderr
    assert "Traceback" in proc.stderr and "ValueError: a bug" in proc.stderr
    assert "error:" not in proc.stderr.splitlines()[0]


def test_every_bad_input_error_is_an_exception_class_of_ours() -> None:
    for module_name, class_name in BAD_INPUT:
        name = resolve_name(module_name, "loopcal.daemon.commands")
        cls = getattr(importlib.import_module(name), class_name)
        assert isinstance(cls, type) and issubclass(cls, Exception), (name, class_name)
        assert cls not in (Exception, ValueError, TypeError, OSError), (name, class_name)


def test_main_prints_a_commands_refusal(capsys) -> None:
    assert main(["files", "no/such/file"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1
    assert err.startswith("loopcal files: error: not shipped: no/such/file (shipped: ")


def test_main_prints_a_domain_error_found_deep_inside(tmp_path: Path, capsys) -> None:
    config = tmp_path / "controller.toml"
    config.write_text("[parameters\n")
    assert main(["upkeep", "status", "--controller-config", str(config)]) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1
    assert err.startswith(f"loopcal upkeep: error: {config}"), err


@pytest.mark.parametrize(("argv", "words"), [
    (["observability", "--noise-mv", "-1"], "--noise-mv must not be negative, got -1"),
    (["observability", "--session", "60", "--noise-mv", "0"], "--noise-mv 0"),
    (["observability", "--poses", "0"], "--poses 0: at least 1"),
    (["demo", "--offset-error", "nan"], "--offset-error must be 0 or more mm, got nan"),
    (["demo", "--twist-every", "-2"], "--twist-every must be 0 or more moves, got -2"),
])  # fmt: skip
def test_the_simulation_options_are_checked_the_same_in_each_command(argv, words,
                                                                      capsys) -> None:  # fmt: skip
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1, err
    assert err.startswith(f"loopcal {argv[0]}: error: ") and words in err, err


@pytest.mark.parametrize("command", ["demo", "simulate", "observability"])
def test_a_bad_pause_is_refused_by_the_parser(command: str, capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main([command, "--pause", "2,1"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert f"loopcal {command}: error: argument --pause: '2,1': need 0 < MIN <= MAX" in err
