"""Kinematics, residuals and the analytic Jacobian."""

import numpy as np
import pytest

from loopcal.calibration.errors import InputError, ParameterError
from loopcal.calibration.kinematics import (
    euler_zyz,
    forward_kinematics,
    from_euler_zyz,
    inverse_kinematics,
    lengths_to_volts,
    plate_home,
    plate_points,
    tilt_swivel,
)
from loopcal.calibration.parameters import (
    NAMES,
    NOMINAL,
    PAPER7,
    ParameterModel,
    Tie,
    check_vector,
    from_dict,
)
from loopcal.calibration.residuals import loop_residuals, reference_points
from loopcal.calibration.simulate import quantize_volts, sample_workspace, simulate_poses


def test_reference_geometry_home_lengths_and_right_angle():
    d = inverse_kinematics(np.eye(3), NOMINAL)[0]
    # docs/model.md: d0 = 97.4 mm is the actuator length at home (to the table's rounding)
    assert np.allclose(d, 97.4, atol=0.03)
    b1, b2 = plate_home(NOMINAL)
    assert np.isclose(np.linalg.norm(b1), 100.0) and np.isclose(np.linalg.norm(b2), 100.0)
    assert abs(b1 @ b2) < 1e-9  # B1 O B2 is a right angle
    assert np.isclose(np.linalg.norm(b1 - b2), 100 * np.sqrt(2))


def test_plate_home_follows_k3():
    p = from_dict({"k3": 120.0})
    b1, b2 = plate_home(p)
    assert np.isclose(np.linalg.norm(b1 - b2), 120.0)


def test_euler_roundtrip_and_workspace_limits():
    rng = np.random.default_rng(0)
    R = sample_workspace(300, rng)
    assert np.allclose(from_euler_zyz(euler_zyz(R)), R, atol=1e-12)
    tilt, swivel = tilt_swivel(R)
    assert tilt.max() <= np.radians(45) + 1e-12
    assert np.abs(swivel).max() <= np.radians(90) + 1e-12
    d = inverse_kinematics(R, NOMINAL)
    assert np.all(np.abs(d - 97.4) <= 37.5)


def test_forward_kinematics_inverts_inverse_kinematics():
    R = sample_workspace(500, np.random.default_rng(1))
    fk = forward_kinematics(inverse_kinematics(R, NOMINAL), NOMINAL)
    assert fk.converged.all()
    assert np.abs(fk.rotations - R).max() < 1e-9
    assert fk.rms_mm.max() < 1e-9
    assert fk.sigma_min.min() > 1.0  # the workspace is free of singularities


def test_loop_residuals_vanish_on_consistent_readings():
    ps = simulate_poses(300, seed=2, noise_volts=0.0, quantize=False)
    ref = plate_points(ps.rotations, ps.truth)
    r = loop_residuals(ps.truth, ps.volts, ref, jacobian=False)
    assert r.feasible.all()
    assert np.abs(r.residuals).max() < 1e-8
    # references from forward kinematics pick the same branches
    r2 = loop_residuals(ps.truth, ps.volts, reference_points(ps.volts, ps.truth), jacobian=False)
    assert np.abs(r2.residuals).max() < 1e-8


def _finite_differences(p, V, ref, step=1e-6):
    J = np.zeros((len(V), 4, len(NAMES)))
    for j in range(len(NAMES)):
        e = np.zeros(len(NAMES))
        e[j] = step * max(1.0, abs(p[j]))
        fp = loop_residuals(p + e, V, ref, jacobian=False).residuals
        fm = loop_residuals(p - e, V, ref, jacobian=False).residuals
        J[:, :, j] = (fp - fm) / (2 * e[j])
    return J


def test_analytic_jacobian_matches_finite_differences_all_20_parameters():
    ps = simulate_poses(200, seed=3)
    p = ps.truth + np.random.default_rng(4).normal(0, 0.3, len(NAMES)) * np.where(
        np.char.startswith(np.array(NAMES), "S"), 0.001, 1.0
    )
    ref = reference_points(ps.volts, p)
    r = loop_residuals(p, ps.volts, ref)
    ok = r.separation.min(axis=1) > 10
    Jfd = _finite_differences(p, ps.volts, ref)
    err = np.abs(r.jacobian[ok] - Jfd[ok]) / (np.abs(Jfd[ok]).max(axis=(0, 1)) + 1e-12)
    assert err.max() < 1e-5


def test_jacobian_where_spheres_miss_is_that_of_the_closest_approach():
    ps = simulate_poses(400, seed=4)
    p = NOMINAL.copy()
    p[16:] += [3.0, -3.0, 3.0, -3.0]
    ref = reference_points(ps.volts, NOMINAL)
    r = loop_residuals(p, ps.volts, ref)
    miss = ~r.feasible
    assert miss.any(), "the scenario should make some sphere triples miss"
    Jfd = _finite_differences(p, ps.volts, ref)
    assert np.abs(r.jacobian[miss] - Jfd[miss]).max() < 1e-5 * np.abs(Jfd[miss]).max()


def test_directions_give_the_reduced_jacobian():
    ps = simulate_poses(50, seed=5)
    ref = reference_points(ps.volts, NOMINAL)
    full = loop_residuals(NOMINAL, ps.volts, ref).jacobian
    red = loop_residuals(NOMINAL, ps.volts, ref, directions=PAPER7.tie_matrix).jacobian
    assert np.allclose(red, full @ PAPER7.tie_matrix, rtol=1e-12, atol=1e-9)


def test_quantisation_matches_the_datasheet_transfer_function():
    codes, v = quantize_volts(np.array([-10.0, -9.9999, 0.0, 9.99, 10.0, 12.0, -12.0]))
    assert codes.tolist() == [0, 0, 2048, 4093, 4095, 4095, 0]
    assert np.isclose(v[2], (2048 + 0.5) * 20 / 4096 - 10)


def test_parameter_model_ties_and_errors():
    m = ParameterModel.parse("d01,A1x", "A4x=-A1x")
    assert m.fixed == tuple(n for n in NAMES if n not in ("d01", "A1x", "A4x"))
    p = m.expand(np.array([98.0, 70.0]), NOMINAL)
    assert p[NAMES.index("A4x")] == pytest.approx(-70.0)
    assert ParameterModel.parse("d03").free == ("d03",)
    assert ParameterModel.parse("paper7") == PAPER7
    with pytest.raises(ParameterError, match="unknown parameter 'Q9'"):
        ParameterModel.parse("d01,Q9")
    with pytest.raises(ParameterError, match="not free"):
        ParameterModel(("d01",), (Tie("A4x", "A1x", -1),))
    with pytest.raises(ParameterError, match="twice"):
        ParameterModel(("d01", "d01"))
    with pytest.raises(ParameterError, match="triangle"):
        inverse_kinematics(np.eye(3), from_dict({"k3": 250.0}))


@pytest.mark.filterwarnings("error")
def test_plates_near_the_largest_float_are_judged_without_an_overflow_warning():
    huge = from_dict({"k1": 1e308, "k2": 1e308, "k3": 1.5e308})
    assert check_vector(huge)[NAMES.index("k3")] == 1.5e308  # a triangle: k1 + k2 is inf
    with pytest.raises(ParameterError, match="triangle"):
        check_vector(from_dict({"k1": 1e308, "k2": 1.0, "k3": 1.0}))


def test_bad_kinematics_input_is_named():
    with pytest.raises(InputError, match="orthonormal"):
        inverse_kinematics(np.ones((2, 3, 3)), NOMINAL)
    with pytest.raises(InputError, match=r"shape \(m, 4\)"):
        forward_kinematics(np.ones((3, 3)), NOMINAL)
    with pytest.raises(InputError, match="NaN"):
        loop_residuals(NOMINAL, np.full((2, 4), np.nan), np.zeros((2, 2, 3)))
    assert lengths_to_volts(np.full((1, 4), 97.4), NOMINAL) == pytest.approx(0.0)


@pytest.mark.parametrize("name", ["reference_points", "start_rotations"])
@pytest.mark.parametrize(
    ("p", "why"),
    [(NOMINAL[:19], r"shape \(20,\), got \(19,\)"),
     (np.where(np.arange(20) == 0, np.nan, NOMINAL), "not finite")],
)  # fmt: skip
def test_a_bad_parameter_vector_is_a_parameter_error_before_it_is_used(name, p, why):
    """As their docstrings say: not a ValueError of broadcasting, nor an InputError about
    the lengths that a NaN gain or offset would make."""
    from loopcal.calibration import implicit, residuals

    f = getattr(residuals, name, None) or getattr(implicit, name)
    with pytest.raises(ParameterError, match=why):
        f(np.zeros((2, 4)), p)
