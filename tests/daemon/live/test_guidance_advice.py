"""The live guidance's advice for a program (``GuidanceUpdate.advice``, ``"advice"`` in
``--json``): the same decision as the instruction the technician reads, update by update."""

from __future__ import annotations

import json

import numpy as np
import pytest

from loopcal.calibration.parameters import PAPER7
from loopcal.daemon.config.controller import nominal_config
from loopcal.daemon.live.guidance import Guidance, GuidanceUpdate
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.scenarios import Static
from tests.support.rows import rows_from
from tests.support.sessions import GuidedSession, hand_rows, truth_for


def _session(rows: np.ndarray, target_mm: float) -> list[GuidanceUpdate]:
    updates: list[GuidanceUpdate] = []
    g = Guidance(nominal_config(), PAPER7, target_mm=target_mm, on_update=updates.append,
                 period_s=0)  # fmt: skip
    for a in range(0, len(rows), 20):
        g.feed(rows[a : a + 20])
        if g.done:
            break
    return updates


@pytest.mark.slow
def test_every_update_tells_a_program_what_it_tells_the_technician():
    # a technician twisting every other move, judged at 0.25 mm: in a minute the guidance asks
    # for a side, passes on a failing gate's own advice, asks for motion anywhere, and stops
    updates = _session(hand_rows(20 * 60, seed=11, twist_every=2), target_mm=0.25)
    kinds = [u.advice.kind for u in updates]
    assert {"tilt", "other", "anywhere", "enough"} <= set(kinds), kinds
    assert kinds[-1] == "enough" and "enough" not in kinds[:-1]
    for u in updates:
        move, doc = u.advice, json.loads(json.dumps(u.as_json()))
        assert doc["advice"] == move.as_json() and doc["instruction"] == u.instruction
        assert (move.kind == "enough") == u.enough
        if move.kind == "other":  # a gate's own advice: the fields say nothing, the text all
            assert move.text == u.instruction and move.sensor is None and move.way is None
            continue
        # the coverage advice, to which the precision gate may add for how long
        rest = u.instruction.removeprefix(move.text)
        assert rest == "" or rest.startswith((", for about", "; at this pace")), rest
        if move.kind == "tilt":
            assert f"toward sensor {move.sensor} (" in u.instruction
            assert f"reach only {move.reached_deg:.0f} deg" in u.instruction
        if not u.gates:  # before the worker runs: from the update's own coverage
            assert move.kind == "tilt"
            assert move.sensor == int(np.argmin(u.reach_deg)) + 1
            assert move.reached_deg == pytest.approx(min(u.reach_deg))


def test_a_plate_left_still_is_told_to_move_anywhere():
    truth = truth_for(3)
    t_us, codes = mechanism_scans(Static((0.0, 12.0, 0.0)), truth, 20 * 12, noise_volts=0.04,
                                  seed=3)  # fmt: skip
    updates = _session(rows_from(t_us, codes), target_mm=0.1)
    assert [u.advice.kind for u in updates[:9]] == ["tilt"] * 9
    last = updates[-1]
    assert last.advice.kind == "anywhere" and last.instruction == last.advice.text
    assert last.instruction.startswith("move the plate: tilt and twist it")
    assert last.as_json()["advice"] == {
        "kind": "anywhere",
        "sensor": None,
        "azimuth_deg": None,
        "aim_deg": None,
        "reached_deg": None,
        "way": None,
    }


@pytest.mark.slow
def test_a_technician_doing_what_it_says_covers_what_it_asks_for_and_is_done():
    """The loop closed offline: the advice of each second steers the guided technician's
    next moves (tests.support.sessions.GuidedSession), as bench_scans --part enough runs it."""
    session = GuidedSession(101)
    updates: list[GuidanceUpdate] = []
    g = Guidance(nominal_config(), PAPER7, target_mm=0.1, on_update=updates.append, period_s=0)
    session.follow(g, 90)
    last = updates[-1]
    assert last.enough and last.advice.kind == "enough" and session.seconds <= 60
    kinds = [u.advice.kind for u in updates]
    # every side, then both twists, then anywhere: asked for in that order, and all reached
    assert kinds.index("tilt") < kinds.index("twist") < kinds.index("anywhere")
    assert "tilt" not in kinds[kinds.index("twist") :]
    assert min(last.reach_deg) >= 25.0 and min(last.twist_deg) >= 30.0
