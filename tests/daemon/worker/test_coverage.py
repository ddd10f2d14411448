"""The tilt and twist coverage of the poses and the advice it gives
(:mod:`loopcal.daemon.worker.coverage`): how far the plate turned each way, the sensor's side
and the twist asked for, readings no pose explains left out, and the advice for a program
(``NextMove``) saying what its text says."""

import json
import re

import numpy as np
import pytest

from loopcal.calibration.implicit import predicted_volts
from loopcal.calibration.kinematics import forward_kinematics, from_euler_zyz, volts_to_lengths
from loopcal.calibration.parameters import NOMINAL
from loopcal.daemon.worker import coverage as C


def _tilted_and_twisted(swivels_deg: list[float], tilt_deg: float = 28.0) -> np.ndarray:
    """Readings (nominal geometry) of the plate tilted ``tilt_deg`` toward eight azimuths
    (every sensor reached), untwisted, plus one small-tilt position per swivel."""
    az = np.radians(np.arange(0, 360, 45))
    tilt = np.column_stack([az, np.full(8, np.radians(tilt_deg)), -az])  # swivel 0
    sw = np.radians(swivels_deg)
    twist = np.column_stack([np.zeros(len(sw)), np.full(len(sw), np.radians(5.0)), sw])
    return predicted_volts(from_euler_zyz(np.vstack([tilt, twist])), NOMINAL)


def test_twist_coverage_is_how_far_the_plate_turned_each_way():
    volts = _tilted_and_twisted([-12.0, 4.0, 21.0, 36.5])
    np.testing.assert_allclose(C.twist_coverage(volts, NOMINAL), [12.0, 36.5], atol=1e-6)
    np.testing.assert_allclose(C.twist_coverage(volts[:8], NOMINAL), [0.0, 0.0], atol=1e-6)
    assert C.twist_coverage(np.zeros((0, 4)), NOMINAL).tolist() == [0.0, 0.0]


def test_once_tilted_every_way_the_advice_asks_to_twist_the_way_least_turned():
    assert (C.coverage(_tilted_and_twisted([]), NOMINAL) >= C.GOOD_TILT_DEG).all()
    advice = C.coverage_advice(_tilted_and_twisted([-12.0, 36.5]), NOMINAL, still=False)
    assert advice.startswith("twist the plate about its own axis, clockwise seen from above")
    assert "reach only 12 deg that way" in advice and "holding" not in advice
    advice = C.coverage_advice(_tilted_and_twisted([-40.0, 8.0]), NOMINAL)
    assert "counter-clockwise" in advice and "reach only 8 deg" in advice and "holding" in advice
    both = C.coverage_advice(_tilted_and_twisted([-40.0, 36.5]), NOMINAL, still=False)
    assert both == "keep moving the plate through the whole workspace, tilting and twisting it"
    # the tilt comes first: a sensor not reached is asked for before any twist
    low = C.coverage_advice(_tilted_and_twisted([], tilt_deg=15.0), NOMINAL, still=False)
    assert low.startswith("tilt the plate further toward sensor")


def test_readings_no_pose_explains_are_left_out_of_the_coverage_not_fatal():
    clean = _tilted_and_twisted([-12.0, 36.5])
    broken = np.array([[9.9, 9.9, -9.9, -9.9]] * 3)  # a damaged channel: no pose fits
    fk = forward_kinematics(volts_to_lengths(broken, NOMINAL), NOMINAL)
    assert not fk.converged.any()
    mixed = np.vstack([clean[:5], broken, clean[5:]])
    reach, twist = C.reach_and_twist(mixed, NOMINAL)
    np.testing.assert_allclose(reach, C.coverage(clean, NOMINAL))
    np.testing.assert_allclose(twist, [12.0, 36.5], atol=1e-6)
    assert C.coverage_advice(mixed, NOMINAL) == C.coverage_advice(clean, NOMINAL)
    assert C.twist_coverage(broken, NOMINAL).tolist() == [0.0, 0.0]
    assert C.coverage(broken, NOMINAL).tolist() == [0.0] * 4


# ---------------------------------------------------------------------------- the next move
# One decision, two renderings: the structured advice (NextMove) and the text a person reads
# must say the same thing. What the text says is read back from its words here.

TILT = re.compile(r"tilt the plate further toward sensor (\d) \(the (scans|poses) reach only "
                  r"(\d+) deg that way; aim for (\d+) deg or more\)")  # fmt: skip
TWIST = re.compile(r"twist the plate about its own axis, (clockwise|counter-clockwise) seen "
                   r"from above \(the (scans|poses) reach only (\d+) deg that way; aim for "
                   r"(\d+) deg or more\)")  # fmt: skip


def _says(move: C.NextMove) -> None:
    """The move's fields are what its text says (and nothing the text does not)."""
    tilt, twist = TILT.match(move.text), TWIST.match(move.text)
    doc = json.loads(json.dumps(move.as_json()))
    assert set(doc) == {"kind", "sensor", "azimuth_deg", "aim_deg", "reached_deg", "way"}
    if move.kind == "tilt":
        assert tilt and not twist, move.text
        assert move.sensor == int(tilt[1]) and doc["sensor"] == move.sensor
        assert round(move.reached_deg) == int(tilt[3]) and move.aim_deg == int(tilt[4])
        az = C.sensor_azimuths(NOMINAL)[move.sensor - 1]
        assert move.azimuth_deg == pytest.approx(az) and doc["azimuth_deg"] == round(az, 1)
        assert move.way is None
    elif move.kind == "twist":
        assert twist and not tilt, move.text
        assert move.way == twist[1] and doc["way"] == twist[1]
        assert round(move.reached_deg) == int(twist[3]) and move.aim_deg == int(twist[4])
        assert move.sensor is None and move.azimuth_deg is None
    else:
        assert move.kind == "anywhere" and not tilt and not twist, move.text
        assert "tilting and twisting" in move.text or "tilted and twisted" in move.text
        assert doc == {"kind": "anywhere", "sensor": None, "azimuth_deg": None,
                       "aim_deg": None, "reached_deg": None, "way": None}  # fmt: skip


def _toward(tilts_deg: list[float]) -> np.ndarray:
    """Readings (nominal geometry) of the plate tilted ``tilts_deg[i]`` toward sensor i + 1
    (exactly at its azimuth), untwisted."""
    az = np.radians(C.sensor_azimuths(NOMINAL))
    R = from_euler_zyz(np.column_stack([az, np.radians(tilts_deg), -az]))
    return predicted_volts(R, NOMINAL)


@pytest.mark.parametrize("missing", [1, 2, 3, 4])
def test_a_side_not_reached_is_asked_for_by_its_sensor_and_direction(missing):
    tilts = [31.0] * 4
    tilts[missing - 1] = 10.0
    volts = _toward(tilts)
    move = C.coverage_move(volts, NOMINAL, still=False)
    assert move.kind == "tilt" and move.sensor == missing
    assert move.reached_deg == pytest.approx(10.0, abs=1e-6) and move.aim_deg == C.GOOD_TILT_DEG
    assert move.text == C.coverage_advice(volts, NOMINAL, still=False)
    assert f"toward sensor {missing} " in move.text and "holding" not in move.text
    _says(move)
    # where sensor 3 is, as a direction: about 65 deg clockwise of sensor 1, seen from above
    assert C.sensor_azimuths(NOMINAL)[2] == pytest.approx(-65.2, abs=0.1)


@pytest.mark.parametrize(("swivels", "way", "reached"),
                         [([-12.0, 36.5], "clockwise", 12.0),
                          ([-40.0, 8.0], "counter-clockwise", 8.0)])  # fmt: skip
def test_the_twist_asked_for_names_its_way_and_how_far(swivels, way, reached):
    for still in (True, False):
        volts = _tilted_and_twisted(swivels)
        move = C.coverage_move(volts, NOMINAL, still=still)
        assert move.kind == "twist" and move.way == way and move.aim_deg == C.GOOD_TWIST_DEG
        assert move.reached_deg == pytest.approx(reached, abs=1e-6)
        assert move.text == C.coverage_advice(volts, NOMINAL, still=still)
        assert ("holding" in move.text) == still
        _says(move)


def test_covered_or_nothing_yet_is_anywhere():
    both = C.coverage_move(_tilted_and_twisted([-40.0, 36.5]), NOMINAL, still=False)
    assert both.kind == "anywhere" and both.text.startswith("keep moving the plate")
    _says(both)
    nothing = C.coverage_move(np.zeros((0, 4)), NOMINAL)
    assert nothing.kind == "anywhere" and "whole range" in nothing.text
    assert nothing.text == C.coverage_advice(np.zeros((0, 4)), NOMINAL)
    _says(nothing)
    with pytest.raises(ValueError, match="kind 'sideways'"):
        C.NextMove("sideways", "")


def test_every_coverage_gets_a_move_its_text_agrees_with():
    """Coverages drawn over the whole range, the thresholds' edges included."""
    rng = np.random.default_rng(29)
    kinds = set()
    for _ in range(400):
        reach = rng.choice([0.0, 12.4, 24.9, 25.0, 31.0, 44.0], 4)
        twist = rng.choice([0.0, 17.6, 29.9, 30.0, 48.0], 2)
        still = bool(rng.integers(2))
        move = C.next_move(reach, twist, NOMINAL, still=still)
        _says(move)
        kinds.add(move.kind)
        if reach.min() < C.GOOD_TILT_DEG:
            assert move.sensor == int(np.argmin(reach)) + 1
        elif twist.min() < C.GOOD_TWIST_DEG:
            assert move.way == C.TWIST_WAYS[int(np.argmin(twist))]
        else:
            assert move.kind == "anywhere"
    assert kinds == {"tilt", "twist", "anywhere"}


def test_the_gates_text_and_the_move_are_made_once_from_one_decision():
    volts = _toward([31.0, 31.0, 8.0, 31.0])
    advice = C.lazy_coverage_advice(volts, NOMINAL, still=False)
    assert not advice.made
    text = advice()
    assert advice.made and advice.move() is advice.move() and text == advice.move().text
    assert advice.move().kind == "tilt" and advice.move().sensor == 3
