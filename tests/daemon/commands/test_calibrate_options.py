"""Options of the commands that identify parameters that would do nothing are refused (issue
32): ``--ties`` with a preset (which brings its own ties), ``calibrate --config`` when the
recordings and the controller config are both given; exit status 2 naming the option, before
anything is read. (``--select`` without ``--method paper`` and observability's session
options: tests/daemon/commands/test_help_matches_parser.py, from their helps.)"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.processes import loopcal_main


@pytest.mark.parametrize("argv", [
    ["observability", "--ties", "A3x=-A2x"],
    ["observability", "--free", "paper7", "--ties", "A3x=-A2x"],
    ["calibrate", "--free", "offsets", "--ties", "d02=d01", "--controller-config", "{tmp}/c.toml",
     "{tmp}/x.mcap"],
])  # fmt: skip
def test_ties_go_with_a_custom_free_set(argv: list[str], tmp_path: Path) -> None:
    """A preset brings its own ties: --ties with one is refused, not read as a parameter
    named after the preset ("unknown parameter 'paper7'")."""
    if "{tmp}/c.toml" in argv:
        assert loopcal_main("init-config", tmp_path / "c.toml").returncode == 0
    proc = loopcal_main(*(a.format(tmp=tmp_path) for a in argv))
    assert proc.returncode == 2, proc.stdout + proc.stderr
    name = argv[0]
    assert proc.stderr.startswith(f"loopcal {name}: error: --ties goes with a custom free set"), \
        proc.stderr  # fmt: skip
    assert "unknown parameter" not in proc.stderr


def test_ties_with_a_custom_free_set_are_taken() -> None:
    proc = loopcal_main("observability", "--free", "d01,d02,A1x,A2x", "--ties", "A4x=-A1x",
                        "--poses", "100")  # fmt: skip
    assert proc.returncode in (0, 1) and proc.stderr == "", proc.stderr


def test_calibrate_refuses_a_config_that_would_give_nothing(tmp_path: Path) -> None:
    """--config gives the recordings directory and the controller config: with both given,
    it would change nothing."""
    proc = loopcal_main("calibrate", tmp_path / "x.mcap", "--controller-config",
                        tmp_path / "c.toml", "--config", tmp_path / "daemon.toml")  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.startswith("loopcal calibrate: error: --config gives the recordings "
                                  "directory and the controller config; both are given"), \
        proc.stderr  # fmt: skip


def test_select_with_the_papers_method_is_taken(tmp_path: Path) -> None:
    """--select goes through with --method paper (to the next check: the recording)."""
    assert loopcal_main("init-config", tmp_path / "c.toml").returncode == 0
    proc = loopcal_main("calibrate", tmp_path / "x.mcap", "--controller-config",
                        tmp_path / "c.toml", "--method", "paper", "--select", "20")  # fmt: skip
    assert proc.returncode == 2 and "--select" not in proc.stderr, proc.stderr
    assert "x.mcap" in proc.stderr


@pytest.mark.parametrize(("argv", "words"), [
    (["calibrate", "--select", "10"], "--select only with --method paper"),
    (["calibrate", "--select", "50", "--method", "ml"], "--select only with --method paper"),
    (["observability", "--noise-mv", "30"], "--noise-mv only with --session"),
    (["observability", "--session", "10", "--poses", "450"], "--poses not with --session"),
])  # fmt: skip
def test_an_option_the_chosen_way_ignores_is_refused(argv: list[str], words: str) -> None:
    """calibrate's default method fits every usable scan and selects none, so --select
    (even its default value, given) would change nothing; observability's still poses are
    noise-free, and a --session judges its scans instead of --poses."""
    proc = loopcal_main(*argv)
    assert proc.returncode == 2 and proc.stdout == "", proc.stdout
    assert proc.stderr.startswith(f"loopcal {argv[0]}: error: {words}: "), proc.stderr
