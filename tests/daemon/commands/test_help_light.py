"""Every ``loopcal X --help`` without the analysis (issue 32): building a command's parser and
printing its help imports none of numpy, scipy, matplotlib, mcap, pymodbus, pyserial,
tomlkit, foxglove, prometheus_client or dask; the commands import their machinery when they
run (docs/architecture.md). Each help is asked of a fresh interpreter, which then says which
of those it loaded. No timing here: bench/bench_help.py times them."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from loopcal.daemon.commands import COMMANDS

#: the packages a help must not wait for (top-level import names)
HEAVY = ("numpy", "scipy", "matplotlib", "mcap", "pymodbus", "serial", "tomlkit", "foxglove",
         "prometheus_client", "dask")  # fmt: skip

#: run in the fresh interpreter: the help printed into a buffer, then what was loaded
_CHILD = """
import contextlib, io, json, sys
from loopcal.daemon.cli import main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        status = main(ARGV)
    except SystemExit as exc:
        status = exc.code
print(json.dumps({"status": status, "help": out.getvalue(),
                  "loaded": sorted(m for m in HEAVY if m in sys.modules)}))
"""


def _help_of(argv: list[str]) -> dict:
    code = _CHILD.replace("ARGV", repr(argv)).replace("HEAVY", repr(HEAVY))
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.splitlines()[-1])


@pytest.mark.parametrize("argv", [["--help"]] + [[name, "--help"] for name, _ in COMMANDS],
                         ids=lambda argv: " ".join(argv))  # fmt: skip
def test_a_help_imports_none_of_the_analysis(argv: list[str]) -> None:
    got = _help_of(argv)
    prog = " ".join(["loopcal", *argv[:-1]])
    assert got["status"] == 0 and got["help"].startswith(f"usage: {prog}"), got
    assert got["loaded"] == [], f"{prog} --help imported {', '.join(got['loaded'])}"
