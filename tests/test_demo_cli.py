"""The README's main command, `loopcal demo`, as a real subprocess: record a technician's
session through the emulated DAQ, calibrate it, write the config, compare with the truth."""

import re
import subprocess
import sys

import pytest

from loopcal.daemon.config.controller import load_controller_config


def run_demo(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "loopcal.daemon.cli", "demo", *args],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip


def test_demo_writes_offsets_close_to_the_truth(tmp_path):
    proc = run_demo("--out", str(tmp_path), "--seed", "2")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = proc.stdout
    assert "$ loopcal record --daq modbus-tcp://127.0.0.1:" in out
    assert "Wrote 10 value(s)" in out
    rows = dict(
        re.findall(r"^\s+(d0\d|A1x|A2x|A2y)\s+mm\s+(\S+\s+\S+\s+\S+\s+\S+\s+\S+)$", out, re.M)
    )
    assert set(rows) == {"d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"}
    written = load_controller_config(tmp_path / "controller.toml")
    for name, cols in rows.items():
        value, truth, error, std, z = (float(v) for v in cols.split())
        assert abs(z) < 3.5 and std < 0.25 and abs(error) < 0.5, name
        assert abs(written.params[written_index(name)] - value) < 1e-3
    assert (tmp_path / "report" / "index.html").exists()
    assert float(re.search(r"Done in ([\d.]+) s", out).group(1)) < 60


def written_index(name: str) -> int:
    from loopcal.calibration.parameters import INDEX

    return INDEX[name]


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--minutes", "0"], "--minutes must be positive"), (["--free", "Q7"], "unknown parameter")],
)
def test_demo_bad_options(args, message):
    proc = run_demo(*args)
    assert proc.returncode == 2
    assert message in proc.stderr
