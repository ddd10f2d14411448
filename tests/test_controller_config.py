"""The controller config: init-config, reading it back, and every way it can be wrong."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import tomlkit

from calibration.parameters import NAMES, NOMINAL
from daemon.controller_config import (
    ControllerConfigError,
    load_controller_config,
    nominal_config,
    render_initial_config,
)


def init_config(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "daemon.cli", "init-config", *args],
                          capture_output=True, text=True, timeout=60)  # fmt: skip


def test_init_config_writes_the_reference_geometry_with_comments(tmp_path):
    path = tmp_path / "controller.toml"
    proc = init_config(str(path))
    assert proc.returncode == 0 and str(path) in proc.stdout
    cfg = load_controller_config(path)
    assert np.array_equal(cfg.params, NOMINAL)  # bit for bit
    assert cfg.free == "paper7" and cfg.ties == ()
    lines = path.read_text().splitlines()
    for name in NAMES:
        i = next(k for k, line in enumerate(lines) if line.startswith(f"{name} = "))
        unit = "mm/V" if name.startswith("S") else "mm"
        assert lines[i - 1].startswith("# ") and lines[i - 1].endswith(f", {unit}"), name


def test_init_config_refuses_to_overwrite_unless_forced(tmp_path):
    path = tmp_path / "controller.toml"
    path.write_text("mine")
    proc = init_config(str(path))
    assert proc.returncode == 2 and "--force" in proc.stderr
    assert path.read_text() == "mine"
    assert init_config(str(path), "--force").returncode == 0
    assert load_controller_config(path).sha256
    missing = init_config(str(tmp_path / "no" / "such" / "dir.toml"))
    assert missing.returncode == 2 and "does not exist" in missing.stderr


def test_editing_one_value_keeps_every_comment(tmp_path):
    text = render_initial_config()
    doc = tomlkit.parse(text)
    doc["parameters"]["d03"] = 99.125
    edited = tomlkit.dumps(doc)
    before, after = text.splitlines(), edited.splitlines()
    changed = [(a, b) for a, b in zip(before, after, strict=True) if a != b]
    assert changed == [("d03 = 97.4", "d03 = 99.125")]
    path = tmp_path / "c.toml"
    path.write_text(edited)
    assert load_controller_config(path).params[NAMES.index("d03")] == 99.125


GOOD = render_initial_config()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", r"no \[parameters\] table"),
        ("[parameters\n", "not valid TOML"),
        (GOOD.replace("d03 = 97.4", 'd03 = "abc"'), r"\[parameters\]\.d03 = 'abc' is not a number"),
        (GOOD.replace("d03 = 97.4", "d03 = true"), r"\[parameters\]\.d03 = True is not a number"),
        (GOOD.replace("d03 = 97.4", "d03 = nan"), r"\[parameters\]\.d03 = nan is not finite"),
        (GOOD.replace("d03 = 97.4\n", ""), r"\[parameters\] lacks d03"),
        (GOOD.replace("d03 = 97.4", "d03 = 97.4\nd3 = 1.0"),
         r"\.d3: unknown parameter \(did you mean d03\?\)"),
        (GOOD.replace("S2 = 3.75", "S2 = -3.75"), r"\[parameters\]: .*S2"),
        (GOOD + "\n[robot]\nname = 'x'\n", r"unknown table or key 'robot'"),
        (GOOD.replace('free = "paper7"', 'free = "Q7"'),
         r"\[calibration\]: unknown parameter 'Q7'"),
        (GOOD.replace('free = "paper7"', "free = 7"), r"\[calibration\]\.free = 7"),
        (GOOD.replace("ties = []", "ties = 'A4x=-A1x'"), r"\[calibration\]\.ties"),
        (GOOD.replace("ties = []", "ties = []\nfreedom = 1"), r"\[calibration\]\.freedom: unknown"),
    ],
)  # fmt: skip
def test_every_problem_names_the_key(tmp_path, text, message):
    path = tmp_path / "controller.toml"
    path.write_text(text)
    with pytest.raises(ControllerConfigError, match=message) as err:
        load_controller_config(path)
    assert str(path) in str(err.value)


def test_unreadable_and_not_utf8(tmp_path):
    with pytest.raises(ControllerConfigError, match="cannot read"):
        load_controller_config(tmp_path / "missing.toml")
    bad = tmp_path / "latin1.toml"
    bad.write_bytes("# caf\xe9\n".encode("latin-1"))
    with pytest.raises(ControllerConfigError, match="not UTF-8"):
        load_controller_config(bad)


def test_metadata_and_model(tmp_path):
    path = tmp_path / "c.toml"
    doc = tomlkit.parse(GOOD)
    doc["calibration"]["free"] = "d03"
    doc["provenance"] = {"written": "2026-11-22T10:00:00Z", "poses": 50}
    path.write_text(tomlkit.dumps(doc))
    cfg = load_controller_config(path)
    meta = cfg.as_metadata()
    assert all(isinstance(v, str) for v in meta.values())
    assert np.array_equal([float(meta[n]) for n in NAMES], cfg.params)
    assert json.loads(meta["provenance"])["poses"] == 50
    assert list(cfg.model().free) == ["d03"]
    assert list(nominal_config().model().free) == ["d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"]
