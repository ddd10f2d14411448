"""Advice that names the cause (issue 32, item 5): a recording too short to tell the
parameters apart is told too little motion, by every gate that fails because of it, and not
to check the geometry, a gain or a sensor; a config whose geometry really is off, on a
recording that pins it down, is still told to check the geometry."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import tomlkit

from loopcal.calibration.simulate import perturbed_truth
from loopcal.simulator.scenarios import HandMoves
from tests.support.processes import fresh_config, loopcal_main
from tests.support.sessions import PAUSE_S, truth_for, write_session

#: the gates that judge whether the motion told the parameters apart
MOTION = {"poses", "condition", "min_singular"}
#: what an advice says when it blames the mechanism or its config
BLAME = re.compile(r"\bgeometry\b|\bgains?\b|\bwiring\b|check sensor|stuck or disconnected")


def _calibrate(rec: Path, config: Path, *extra: str) -> dict:
    proc = loopcal_main("calibrate", rec, "--controller-config", config, "--json", *extra)
    assert proc.returncode == 1, proc.stderr
    return json.loads(proc.stdout)


def _demo_session(path: Path, seconds: float, seed: int, twist_every: int = 2) -> Path:
    """A technician's session as ``loopcal demo`` simulates one (refitted LVDTs, offsets up
    to 3 mm off; twisting every ``twist_every`` moves), ``seconds`` long."""
    truth = perturbed_truth(np.random.default_rng(seed), offsets_mm=3.0)
    write_session(path, HandMoves(seed, params=truth, pause_s=PAUSE_S, twist_every=twist_every),
                  truth, seconds, seed=seed)  # fmt: skip
    return path


@pytest.mark.parametrize("method", ["ml", "paper"])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_three_seconds_are_told_too_little_motion(seed: int, method: str, tmp_path: Path) -> None:
    """3 s of a demo's session: refused for too little motion (seed 2: sensor 3 hardly
    moved in those 3 s, which is not yet a stuck sensor)."""
    rec = _demo_session(tmp_path / "rec", 3, seed)
    doc = _calibrate(rec, fresh_config(tmp_path / "c.toml"), "--method", method)
    failed = [g for g in doc["gates"] if not g["passed"]]
    assert failed and failed[0]["name"] == "poses", failed
    assert failed[0]["reason"].startswith("too little motion: "), failed[0]
    for g in failed:
        assert not BLAME.search(g["reason"] + g["advice"]), g


@pytest.mark.parametrize(("seconds", "seed", "twist_every"), [(5, 3, 0), (8, 1, 0), (8, 5, 2)])
def test_a_short_recording_blames_the_motion_not_the_geometry(seconds: float, seed: int,
                                                              twist_every: int,
                                                              tmp_path: Path) -> None:  # fmt: skip
    """A few seconds that pass the poses gate but do not tell the seven parameters apart:
    A1x or A2y lands millimetres off with a standard deviation as large, and plausible
    fails. It was told to "check the controller config's geometry against the mechanism";
    every gate that fails for the motion now says too little motion first, with the
    positions and seconds it had."""
    rec = _demo_session(tmp_path / "rec", seconds, seed, twist_every)
    doc = _calibrate(rec, fresh_config(tmp_path / "c.toml"))
    failed = {g["name"]: g for g in doc["gates"] if not g["passed"]}
    assert "plausible" in failed, failed
    for g in failed.values():
        assert not BLAME.search(g["advice"]), g
    assert failed["plausible"]["advice"].startswith("too little motion: "), failed["plausible"]
    assert f"over {seconds} s, the workspace is not covered" in failed["plausible"]["advice"]
    assert "not told apart from none" in failed["plausible"]["reason"]
    if MOTION & set(failed):  # every other failure follows from the motion's
        for name, g in failed.items():
            if name not in MOTION:
                assert g["advice"].startswith("too little motion: "), g


def test_a_geometry_that_is_off_is_still_told_so(tmp_path: Path) -> None:
    """Two minutes of motion against a config whose A1x (and A4x, tied to it) is 5 mm off:
    every gate on the motion passes, A1x moves by about 5 mm known to a tenth of a mm, and
    plausible names the geometry."""
    truth = truth_for(3)
    write_session(tmp_path / "rec", HandMoves(3, params=truth, pause_s=PAUSE_S), truth, 120,
                  seed=3)  # fmt: skip
    config = fresh_config(tmp_path / "c.toml")
    doc = tomlkit.parse(config.read_text())
    doc["parameters"]["A1x"] = float(doc["parameters"]["A1x"]) + 5.0
    doc["parameters"]["A4x"] = float(doc["parameters"]["A4x"]) - 5.0
    config.write_text(tomlkit.dumps(doc))
    out = _calibrate(tmp_path / "rec", config)
    failed = {g["name"]: g for g in out["gates"] if not g["passed"]}
    assert set(failed) == {"plausible"}, failed
    assert failed["plausible"]["advice"] == "check the controller config's geometry against " \
        "the mechanism"  # fmt: skip
    assert failed["plausible"]["value"].startswith("A1x -4.")
