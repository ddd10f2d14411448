"""Identification: exact recovery, calibrated uncertainty, and clear errors."""

import numpy as np
import pytest

from loopcal.calibration.errors import InputError, UnobservableError
from loopcal.calibration.identify import identify
from loopcal.calibration.parameters import NOMINAL, PAPER7, PRESETS, from_dict
from loopcal.calibration.selection import candidate_jacobian, select_poses
from loopcal.calibration.simulate import perturbed_truth, simulate_poses


@pytest.mark.parametrize("signs", [(1, 1, 1, 1), (1, -1, 1, -1), (-1, -1, 1, 1)])
def test_noise_free_truth_recovered_from_offsets_3mm_off(signs):
    ps = simulate_poses(200, seed=3, noise_volts=0.0, quantize=False)
    start = ps.truth.copy()
    start[16:] += 3.0 * np.array(signs)
    start[[0, 1, 2, 3, 4, 6]] = NOMINAL[[0, 1, 2, 3, 4, 6]]  # geometry at the blueprint
    res = identify(ps.volts, PAPER7, start)
    assert res.converged
    assert np.abs(res.params - ps.truth).max() < 1e-6
    # tied parameters stay tied
    assert res.params[3] == pytest.approx(-res.params[1], abs=1e-12)
    assert res.params[6] == pytest.approx(-res.params[0], abs=1e-12)


def test_only_d03_after_replacing_sensor_3():
    rng = np.random.default_rng(7)
    truth = NOMINAL.copy()
    truth[18] += 2.4
    ps = simulate_poses(100, truth=truth, seed=rng)
    res = identify(ps.volts, PRESETS["d03"], NOMINAL)
    assert res.model.free == ("d03",)
    assert abs(res.params[18] - truth[18]) < 3 * res.std[0]
    assert res.std[0] < 0.1
    # every other parameter untouched
    others = np.arange(20) != 18
    assert np.array_equal(res.params[others], NOMINAL[others])


@pytest.mark.slow
def test_paper_noise_50_selected_poses_offsets_within_3_sigma_over_seeds():
    z_all = []
    for seed in range(12):
        ps = simulate_poses(450, seed=seed, noise_volts=0.040)
        c = candidate_jacobian(ps.volts, PAPER7, NOMINAL)
        sel = select_poses(c.jacobian, 50, certify=False, information=c.information)
        res = identify(ps.volts[sel.indices], PAPER7, NOMINAL)
        assert res.converged, res.message
        z = (res.params - ps.truth)[16:20] / res.std[:4]
        assert np.all(np.abs(z) < 3.0), (seed, z)
        assert np.all(res.std[:4] < 0.5)
        z_all.append(z)
    z_all = np.concatenate(z_all)
    # the predicted standard deviations are honest: z-scores have RMS near one
    assert 0.6 < np.sqrt(np.mean(z_all**2)) < 1.5


def test_noise_estimate_matches_the_simulated_noise():
    ps = simulate_poses(450, seed=11, noise_volts=0.040)
    res = identify(ps.volts, PAPER7, NOMINAL)
    assert res.sigma_estimated
    assert 0.034 < res.sigma_volts < 0.046
    given = identify(ps.volts, PAPER7, NOMINAL, noise_volts=0.040)
    assert not given.sigma_estimated
    assert np.allclose(given.params, res.params)


def test_bad_input_raises_clear_errors():
    ps = simulate_poses(30, seed=1)
    V = ps.volts.copy()
    V[4, 2] = np.nan
    with pytest.raises(InputError, match=r"NaN.*pose 4, sensor 3"):
        identify(V, PAPER7)
    V = ps.volts.copy()
    V[7, 1] = 10.5  # 39.4 mm of travel
    with pytest.raises(InputError, match=r"outside the \+-10 V span.*pose 7, sensor 2"):
        identify(V, PAPER7)
    with pytest.raises(InputError, match="5 poses cannot identify 7 free parameters"):
        identify(ps.volts[:5], PAPER7)
    with pytest.raises(InputError, match=r"shape \(m, 4\)"):
        identify(ps.volts[:, :3], PAPER7)


def test_unobservable_free_set_is_refused_naming_the_combination():
    # Loop closure uses distances only: scaling every length (geometry, gains and offsets)
    # together leaves every loop closed, so the full set has an exact blind direction.
    ps = simulate_poses(100, seed=2, noise_volts=0.0, quantize=False)
    with pytest.raises(UnobservableError) as err:
        identify(ps.volts, PRESETS["all"], ps.truth)
    assert "cannot be identified" in str(err.value)
    assert err.value.combinations
    # the scale invariance itself: every loop stays closed at 1.1 times the true parameters
    from loopcal.calibration.kinematics import plate_points
    from loopcal.calibration.residuals import loop_residuals

    ref = 1.1 * plate_points(ps.rotations, ps.truth)
    scaled = loop_residuals(1.1 * ps.truth, ps.volts, ref, jacobian=False)
    assert np.abs(scaled.residuals).max() < 1e-8


@pytest.mark.parametrize(
    ("method", "misfit", "exact_fit"), [("paper", 1.0, 1e-6), ("ml", 1e-3, 1e-9)]
)
def test_gain_error_beyond_tolerance_is_reported_not_hidden(method, misfit, exact_fit):
    # the paper: with gains held 1 % off, the offsets absorb the error; the fit must still
    # end with a clear status and a residual far above the noise (mm^2 for the paper's
    # loop residuals, V for maximum likelihood)
    truth = perturbed_truth(np.random.default_rng(5))
    ps = simulate_poses(200, truth=truth, seed=5, noise_volts=0.0, quantize=False)
    start = from_dict({"S1": 3.75 * 1.01, "S3": 3.75 * 0.99})
    res = identify(ps.volts, PAPER7, start, method=method)
    assert res.converged and res.method == method
    assert res.rms_residual > misfit
    exact = identify(ps.volts, PAPER7, NOMINAL, method=method)
    assert exact.rms_residual < exact_fit


@pytest.mark.slow
def test_readings_that_do_not_fit_are_flagged():
    ps = simulate_poses(300, seed=1)
    good = identify(ps.volts, PAPER7)
    assert good.problems() == []
    V = ps.volts.copy()
    V[:, 2] = V[np.random.default_rng(0).permutation(300), 2]  # channel 3 wired to junk
    bad = identify(V, PAPER7)
    text = " ".join(bad.problems())
    assert "do not fit the model" in text


def test_calibrate_selects_then_identifies_in_rounds():
    from loopcal.calibration.pipeline import calibrate

    ps = simulate_poses(450, seed=21)
    cal = calibrate(ps.volts, PAPER7, NOMINAL, n_select=50)
    res = cal.identification
    assert len(cal.selection.indices) == 50 and 1 <= cal.rounds <= 2
    assert res.converged and res.problems() == []
    z = (res.params - ps.truth)[16:20] / res.std[:4]
    assert np.all(np.abs(z) < 3)
    few = calibrate(ps.volts[:30], PAPER7, NOMINAL, n_select=50)  # fewer than asked: all used
    assert len(few.selection.indices) <= 30


def test_still_poses_average_the_pauses():
    from loopcal.calibration.errors import InputError as _InputError
    from loopcal.calibration.poses import still_poses

    rng = np.random.default_rng(0)
    level = np.array([[1.0, -2.0, 0.5, 3.0], [2.0, 1.0, -1.0, 0.0]])
    ramp = np.linspace(level[0], level[1], 40)
    V = np.concatenate([np.repeat(level[:1], 60, 0), ramp, np.repeat(level[1:], 80, 0)])
    V = V + rng.normal(0, 0.04, V.shape)
    valid = np.ones(len(V), dtype=bool)
    valid[150] = False  # a rail or fault scan splits the second pause
    sp = still_poses(V, valid=valid)
    assert len(sp) == 3
    assert np.allclose(sp.volts[0], level[0], atol=0.03)
    assert np.allclose(sp.volts[-1], level[1], atol=0.03)
    assert sp.ranges[0, 0] == 0 and sp.ranges[-1, 1] == len(V)
    assert np.all(sp.spread < 0.06)
    assert len(still_poses(V, max_scans=20)) > 5
    with pytest.raises(_InputError, match="window"):
        still_poses(V, window=1)


def test_divergence_is_an_error_not_a_result():
    from loopcal.calibration.errors import ConvergenceError

    ps = simulate_poses(100, seed=4, noise_volts=0.0, quantize=False)
    start = ps.truth.copy()
    start[16:] += 3.0
    # the answer lies 3 mm away; forbidding moves beyond 1 mm must end in a clear error
    with pytest.raises(ConvergenceError, match=r"A1x moved more than 1.0"):
        identify(ps.volts, PAPER7, start, max_change=1.0)


def test_observability_indices_follow_their_definitions():
    from loopcal.calibration.observability import observability_indices

    s = np.array([4.0, 2.0, 0.5])
    J = np.zeros((8, 3))  # two poses, 4 rows each
    J[[0, 1, 2], [0, 1, 2]] = s
    ix = observability_indices(J, scales=np.ones(3))
    assert ix.n_poses == 2
    assert ix.min_singular == pytest.approx(0.5)
    assert ix.condition == pytest.approx(8.0)
    assert ix.volume == pytest.approx((4 * 2 * 0.5) ** (1 / 3) / np.sqrt(2))
    assert ix.noise_amplification == pytest.approx(0.25 / 4)
    assert ix.a_optimality == pytest.approx(1 / 16 + 1 / 4 + 4)
    # default scaling: every column to RMS one per pose
    unit = observability_indices(J)
    assert np.allclose(unit.singular_values, np.sqrt(2))
