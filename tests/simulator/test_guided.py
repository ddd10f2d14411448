"""The guided technician (``GuidedHand``): goes where the live guidance's advice says, more
often than not, with a person's imprecision (roughly where told, sometimes a move late or
the wrong way), bounded, seeded and deterministic, and always inside the workspace."""

from __future__ import annotations

import numpy as np
import pytest

from loopcal.calibration.errors import InputError
from loopcal.calibration.kinematics import base_points, output_axis_angles, tilt_swivel
from loopcal.calibration.parameters import NOMINAL
from loopcal.calibration.simulate import perturbed_truth, reachable
from loopcal.simulator.scenarios import GuidedHand, HandMoves

AZIMUTH = np.degrees(np.arctan2(base_points(NOMINAL)[:, 1], base_points(NOMINAL)[:, 0]))


def _tilt(sensor: int) -> dict:
    """The guidance's advice to tilt toward ``sensor``, as its JSON says it."""
    return {"kind": "tilt", "sensor": sensor, "azimuth_deg": round(AZIMUTH[sensor - 1], 1),
            "aim_deg": 25.0, "reached_deg": 3.0, "way": None}  # fmt: skip


def _twist(way: str) -> dict:
    return {"kind": "twist", "sensor": None, "azimuth_deg": None, "aim_deg": 30.0,
            "reached_deg": 0.0, "way": way}  # fmt: skip


def _targets(h: GuidedHand, until: float, after: float = 0.0) -> np.ndarray:
    """(m, 3, 3) where each move that starts after ``after`` and ends by ``until`` ended."""
    ends = [b for a, b, moving in h.segments_until(until) if moving and after < a and b <= until]
    return h.rotation(np.array(ends))


def _off(azimuth: np.ndarray, toward: float) -> np.ndarray:
    """Signed angle from ``toward`` to ``azimuth``, degrees, in [-180, 180)."""
    return (azimuth - toward + 180.0) % 360.0 - 180.0


@pytest.mark.slow
def test_a_tilt_asked_for_is_reached_roughly_more_often_than_not():
    for sensor in (1, 2, 3, 4):
        h = GuidedHand(sensor, params=NOMINAL)
        h.steer(_tilt(sensor), 0.0)
        tilt, azimuth = np.degrees(output_axis_angles(_targets(h, 120.0)))
        off = _off(azimuth, AZIMUTH[sensor - 1])
        there = np.abs(off) <= 45  # within the sector the guidance counts as that side
        assert len(tilt) >= 30 and there.mean() >= 0.7, (sensor, there.mean())
        assert (np.abs(off) >= 135).mean() <= 0.3  # the wrong way: sometimes, not often
        # roughly: off by several degrees, not by tens; tilted about as far as asked
        assert 4.0 <= np.std(off[there]) <= 20.0 and np.abs(off[there]).max() <= 45.0
        assert np.median(tilt[there]) >= 25.0 and tilt.max() <= 45.0
        assert 15.0 <= tilt[there].min()


def test_a_twist_asked_for_goes_that_way_more_often_than_not():
    for seed, way, sign in ((1, "clockwise", -1.0), (2, "counter-clockwise", 1.0)):
        h = GuidedHand(seed, params=NOMINAL)
        h.steer(_twist(way), 0.0)
        R = _targets(h, 120.0)
        swivel = sign * np.degrees(tilt_swivel(R)[1])
        tilt = np.degrees(output_axis_angles(R)[0])
        right = swivel > 0
        assert len(R) >= 30 and 0.7 <= right.mean() < 1.0, right.mean()  # wrong sometimes
        assert np.median(swivel[right]) >= 28.0 and swivel[right].max() <= 30.0 + 10.0 + 20.0
        assert tilt.max() <= h.side_deg + 1e-9  # a twist barely tilts


@pytest.mark.slow
def test_a_change_of_advice_is_followed_a_move_or_two_late_at_most_mostly():
    first_late, third_late = [], []
    for seed in range(30):
        h = GuidedHand(seed, params=NOMINAL, late=0.5, wrong=0.0)
        h.steer(_tilt(1), 0.0)
        h.rotation(np.array([9.99]))
        h.steer(_tilt(4), 10.0)
        _, azimuth = np.degrees(output_axis_angles(_targets(h, 25.0, after=10.0)))
        assert len(azimuth) >= 3
        still_on_one = np.abs(_off(azimuth, AZIMUTH[0])) <= 45
        first_late.append(still_on_one[0])
        third_late.append(still_on_one[:3].all())
        assert (np.abs(_off(azimuth[~still_on_one], AZIMUTH[3])) <= 45).all()
    assert 0.25 <= np.mean(first_late) <= 0.75 and np.mean(third_late) <= 0.25
    prompt = GuidedHand(0, params=NOMINAL, late=0.0, wrong=0.0)
    prompt.steer(_tilt(1), 0.0)
    prompt.rotation(np.array([9.99]))
    prompt.steer(_tilt(4), 10.0)
    _, azimuth = np.degrees(output_axis_angles(_targets(prompt, 25.0, after=10.0)))
    assert (np.abs(_off(azimuth, AZIMUTH[3])) <= 45).all()


def test_the_motion_is_the_seed_and_the_advice_whatever_order_it_is_asked_in():
    truth = perturbed_truth(np.random.default_rng(4))
    t = np.linspace(0.0, 40.0, 801)
    live = GuidedHand(7, params=truth)  # steered a second at a time, as the bench does
    advice = [_tilt(2), _tilt(2), _tilt(3), _twist("clockwise"), {"kind": "anywhere"}]
    for k in range(40):
        live.steer(advice[min(k // 8, 4)], float(k))
        live.rotation(np.array([k + 0.999]))
    again = GuidedHand(7, params=truth)
    for k in range(40):
        again.steer(advice[min(k // 8, 4)], float(k))
    assert np.array_equal(again.rotation(t[::-1])[::-1], live.rotation(t))
    other = GuidedHand(8, params=truth)
    for k in range(40):
        other.steer(advice[min(k // 8, 4)], float(k))
    assert not np.allclose(other.rotation(t), live.rotation(t))
    assert reachable(live.rotation(np.linspace(0, 40, 2000)), truth, margin_mm=9.0).all()
    # without advice, or told to move anywhere, it is the technician who twists every other move
    free = GuidedHand(5, params=truth, pause_s=(0.8, 1.5))
    plain = HandMoves(5, params=truth, pause_s=(0.8, 1.5), twist_every=2)
    assert np.array_equal(free.rotation(t), plain.rotation(t))
    assert free.describe()["name"] == "guided" and free.describe()["wrong"] == 0.15


def test_enough_holds_the_plate_and_what_cannot_be_followed_is_refused():
    h = GuidedHand(3, params=NOMINAL)
    h.steer({"kind": "enough"}, 0.0)
    R = h.rotation(np.linspace(0.0, 20.0, 50))
    assert np.abs(R - np.eye(3)).max() == 0.0
    h.rotation(np.array([30.0]))
    with pytest.raises(ValueError, match="too late"):
        h.steer(_tilt(1), 5.0)  # the motion up to 30 s is decided
    for bad in ({"kind": "sideways"}, {"kind": "tilt", "aim_deg": 25.0},
                {"kind": "twist", "aim_deg": 30.0, "way": "up"}, {"kind": "twist"}):  # fmt: skip
        with pytest.raises(ValueError, match="advice"):
            GuidedHand(3).steer(bad, 0.0)
    # a tilt named by its sensor alone goes toward that sensor's side
    by_sensor, by_azimuth = GuidedHand(3), GuidedHand(3)
    by_sensor.steer({"kind": "tilt", "sensor": 2, "aim_deg": 25.0}, 0.0)
    by_azimuth.steer({**_tilt(2), "azimuth_deg": float(AZIMUTH[1])}, 0.0)
    t = np.linspace(0.0, 20.0, 100)
    assert np.array_equal(by_sensor.rotation(t), by_azimuth.rotation(t))
    for bad_kw in ({"late": 1.5}, {"wrong": -0.1}, {"aim_sd_deg": -1.0}, {"twist_every": -1}):
        with pytest.raises(InputError):
            GuidedHand(3, **bad_kw)
