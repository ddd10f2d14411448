"""The README's main command, `loopcal demo`, as a real subprocess."""

import re
import subprocess
import sys

import pytest


def run_demo(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "daemon.cli", "demo", *args],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip


def test_demo_recovers_the_offsets_through_the_emulated_daq():
    proc = run_demo("--minutes", "3")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = proc.stdout
    assert "modbus-tcp://127.0.0.1:" in out
    assert "0 missed" in out
    rows = dict(re.findall(r"^\s+(d0\d)\s+mm(.*)$", out, re.M))
    assert set(rows) == {"d01", "d02", "d03", "d04"}
    for cols in rows.values():
        _, estimate, std, truth, error, z = (float(v) for v in cols.split())
        assert abs(z) < 3 and std < 0.1 and abs(error) < 0.3
    assert "New sensor offsets: d01 = " in out


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--minutes", "0"], "--minutes must be positive"), (["--free", "Q7"], "unknown parameter")],
)
def test_demo_bad_options(args, message):
    proc = run_demo(*args)
    assert proc.returncode == 2
    assert message in proc.stderr
