"""The acceptance gates after issue #16: the holdout gate's chi-square quantile without
scipy.special (a fifth of a second to import), and the coverage advice made only when a
gate fails and needs it. Same limits, same verdicts, same advice."""

import numpy as np
import pytest
from scipy.special import chdtri

from loopcal.calibration.implicit import predicted_volts
from loopcal.calibration.kinematics import forward_kinematics, from_euler_zyz, volts_to_lengths
from loopcal.calibration.parameters import NOMINAL
from loopcal.calibration.simulate import simulate_poses
from loopcal.daemon.worker import gates as G


@pytest.mark.parametrize("tail", [0.001, 0.01, 0.1, 1e-6])
def test_chi2_quantile_is_scipys(tail):
    dofs = [*range(1, 400), 500, 1000, 1999, 5000, 6062, 10_000, 30_311, 100_000, 1_000_000]
    for dof in dofs:
        assert G.chi2_quantile(dof, tail) == pytest.approx(chdtri(dof, tail), rel=1e-12, abs=0)


def test_chi2_quantile_refuses_what_it_was_not_made_for():
    for dof, tail in ((0, 0.001), (5, 0.5), (5, 0.0)):
        with pytest.raises(ValueError):
            G.chi2_quantile(dof, tail)


def test_holdout_gate_as_before():
    rng = np.random.default_rng(0)
    for n in (4, 5, 9, 40, 1259, 6062):
        for scale in (0.9, 1.0, 1.3, 2.5):
            z = rng.normal(0, scale, n)
            gate = G.holdout_gate(z)
            if n < 5:
                assert not gate.passed
                continue
            rms = float(np.sqrt(np.mean(z**2)))
            limit = G.HOLDOUT_MARGIN * float(np.sqrt(chdtri(n, 0.001) / n))
            assert gate.passed == (rms <= limit)
            assert gate.limit == f"<= {limit:.2f} (RMS in predicted standard deviations, {n} poses)"


def test_advice_is_made_only_for_a_failing_gate(monkeypatch):
    ps = simulate_poses(60, seed=3)
    volts, params = ps.volts, ps.truth
    calls = []
    original = G.coverage_advice

    def counted(v, p, **kw):
        calls.append(1)
        return original(v, p, **kw)

    monkeypatch.setattr(G, "coverage_advice", counted)
    advice = G.lazy_coverage_advice(volts, params)
    assert G.condition_gate(10.0, advice).passed
    assert G.min_singular_gate(1.0, advice).passed
    assert G.precision_gate(["d01"], np.array([0.01]), advice).passed
    assert calls == []
    failed = [
        G.condition_gate(1e4, advice),
        G.min_singular_gate(0.01, advice),
        G.precision_gate(["d01"], np.array([1.0]), advice),
    ]
    assert len(calls) == 1  # made once, for all three
    monkeypatch.undo()
    expected = G.coverage_advice(volts, params)
    assert all(not g.passed and g.advice == expected for g in failed)
    assert G.condition_gate(1e4, expected).advice == expected  # the text still works


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
    np.testing.assert_allclose(G.twist_coverage(volts, NOMINAL), [12.0, 36.5], atol=1e-6)
    np.testing.assert_allclose(G.twist_coverage(volts[:8], NOMINAL), [0.0, 0.0], atol=1e-6)
    assert G.twist_coverage(np.zeros((0, 4)), NOMINAL).tolist() == [0.0, 0.0]


def test_once_tilted_every_way_the_advice_asks_to_twist_the_way_least_turned():
    assert (G.coverage(_tilted_and_twisted([]), NOMINAL) >= G.GOOD_TILT_DEG).all()
    advice = G.coverage_advice(_tilted_and_twisted([-12.0, 36.5]), NOMINAL, still=False)
    assert advice.startswith("twist the plate about its own axis, clockwise seen from above")
    assert "reach only 12 deg that way" in advice and "holding" not in advice
    advice = G.coverage_advice(_tilted_and_twisted([-40.0, 8.0]), NOMINAL)
    assert "counter-clockwise" in advice and "reach only 8 deg" in advice and "holding" in advice
    both = G.coverage_advice(_tilted_and_twisted([-40.0, 36.5]), NOMINAL, still=False)
    assert both == "keep moving the plate through the whole workspace, tilting and twisting it"
    # the tilt comes first: a sensor not reached is asked for before any twist
    low = G.coverage_advice(_tilted_and_twisted([], tilt_deg=15.0), NOMINAL, still=False)
    assert low.startswith("tilt the plate further toward sensor")


def test_readings_no_pose_explains_are_left_out_of_the_coverage_not_fatal():
    clean = _tilted_and_twisted([-12.0, 36.5])
    broken = np.array([[9.9, 9.9, -9.9, -9.9]] * 3)  # a damaged channel: no pose fits
    fk = forward_kinematics(volts_to_lengths(broken, NOMINAL), NOMINAL)
    assert not fk.converged.any()
    mixed = np.vstack([clean[:5], broken, clean[5:]])
    reach, twist = G.reach_and_twist(mixed, NOMINAL)
    np.testing.assert_allclose(reach, G.coverage(clean, NOMINAL))
    np.testing.assert_allclose(twist, [12.0, 36.5], atol=1e-6)
    assert G.coverage_advice(mixed, NOMINAL) == G.coverage_advice(clean, NOMINAL)
    assert G.twist_coverage(broken, NOMINAL).tolist() == [0.0, 0.0]
    assert G.coverage(broken, NOMINAL).tolist() == [0.0] * 4
