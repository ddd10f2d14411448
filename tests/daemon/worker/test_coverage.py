"""The tilt and twist coverage of the poses and the advice it gives
(:mod:`loopcal.daemon.worker.coverage`): how far the plate turned each way, the sensor's side
and the twist asked for, and readings no pose explains left out."""

import numpy as np

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
