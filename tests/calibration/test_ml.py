"""Maximum-likelihood calibration (the implicit loop method): derivatives, recovery,
the Cramér-Rao bound against a Monte Carlo run, selection on its information, bad input."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from loopcal.calibration import implicit
from loopcal.calibration.errors import InputError
from loopcal.calibration.identify import identify
from loopcal.calibration.kinematics import home_derivative, plate_home
from loopcal.calibration.parameters import NOMINAL, PAPER7, PRESETS, ParameterModel
from loopcal.calibration.pipeline import calibrate
from loopcal.calibration.selection import ml_candidates, select_poses
from loopcal.calibration.simulate import perturbed_truth, readings, sample_workspace, simulate_poses


def poses(n: int, rng: np.random.Generator, truth: np.ndarray) -> np.ndarray:
    """n reachable rotations whose readings stay 0.2 V inside the span (noise never rails)."""
    R = sample_workspace(3 * n, rng, truth)
    inside = np.abs(implicit.predicted_volts(R, truth)).max(axis=1) < 9.8
    assert inside.sum() >= n
    return R[inside][:n]


def test_home_derivative_matches_finite_differences():
    p = perturbed_truth(np.random.default_rng(1), model=PRESETS["all"])
    D = home_derivative(p)
    for j, i in enumerate((9, 10, 11)):
        h = 1e-6
        up, down = p.copy(), p.copy()
        up[i] += h
        down[i] -= h
        fd = (plate_home(up) - plate_home(down)) / (2 * h)
        assert np.allclose(D[j], fd, atol=1e-8), (j, D[j], fd)


def test_model_derivatives_match_finite_differences():
    rng = np.random.default_rng(2)
    p = perturbed_truth(rng, model=PRESETS["all"])
    R = sample_workspace(20, rng, p)
    vhat, Jp, Jr = implicit.model_jacobians(R, p)
    assert np.allclose(vhat, implicit.predicted_volts(R, p))
    h = 1e-6
    for i in range(20):
        up, down = p.copy(), p.copy()
        up[i] += h
        down[i] -= h
        fd = (implicit.predicted_volts(R, up) - implicit.predicted_volts(R, down)) / (2 * h)
        assert np.allclose(Jp[:, :, i], fd, rtol=1e-6, atol=1e-8), i
    for a in range(3):
        w = np.zeros(3)
        w[a] = h
        plus = Rotation.from_rotvec(w).as_matrix() @ R
        minus = Rotation.from_rotvec(-w).as_matrix() @ R
        fd = (implicit.predicted_volts(plus, p) - implicit.predicted_volts(minus, p)) / (2 * h)
        assert np.allclose(Jr[:, :, a], fd, rtol=1e-6, atol=1e-7), a


@pytest.mark.parametrize(
    "model",
    [
        PAPER7,
        PRESETS["offsets"],
        ParameterModel(("d01", "d02", "d03", "d04", "A1x", "A2x", "A2y", "S1", "S3", "k3")),
    ],
    ids=["paper7", "offsets", "ten"],
)
def test_noise_free_recovery_from_offsets_three_mm_off(model):
    rng = np.random.default_rng(3)
    truth = perturbed_truth(rng, model=model)
    truth[12:16] = NOMINAL[12:16] + (truth[12:16] - NOMINAL[12:16]) * 0.1  # gains within 1.5 %
    ps = readings(poses(120, rng, truth), truth, rng, noise_volts=0.0, quantize=False)
    start = NOMINAL.copy()
    assert np.abs(model.free_values(truth) - model.free_values(start)).max() > 1.5
    res = identify(ps.volts, model, start, method="ml")
    assert res.converged and res.method == "ml" and len(res.excluded) == 0
    assert np.abs(res.params - truth).max() < 1e-8
    # the estimated rotations are the true ones
    assert np.abs(res.rotations - ps.rotations).max() < 1e-9


@pytest.mark.slow
def test_the_bound_matches_a_monte_carlo_run_and_ml_is_unbiased():
    """300 noisy readings of the same 50 poses: the estimates' covariance is the Cramér-Rao
    bound within its sampling error, their mean is the truth within its standard error."""
    rng = np.random.default_rng(4)
    truth = perturbed_truth(rng)
    R = poses(50, rng, truth)
    sigma = 0.04
    bound = implicit.cramer_rao(R, truth, PAPER7.tie_matrix, noise_volts=sigma)
    clean = implicit.predicted_volts(R, truth)
    runs = 300
    est = np.empty((runs, PAPER7.n_free))
    stds = np.empty((runs, PAPER7.n_free))
    for k in range(runs):
        V = clean + rng.normal(0.0, sigma, clean.shape)
        res = identify(V, PAPER7, NOMINAL, method="ml", noise_volts=sigma)
        est[k] = PAPER7.free_values(res.params)
        stds[k] = res.std
    err = est - PAPER7.free_values(truth)
    var_ratio = err.var(axis=0, ddof=1) / np.diag(bound)
    # a variance from 300 samples scatters by sqrt(2 / 299) = 8 %: allow 3.5 of those
    assert np.all(np.abs(var_ratio - 1) < 3.5 * np.sqrt(2 / (runs - 1))), var_ratio
    z_mean = err.mean(axis=0) / (err.std(axis=0, ddof=1) / np.sqrt(runs))
    assert np.all(np.abs(z_mean) < 3.5), z_mean
    # the covariance it reports (known noise) is the bound at its own estimate
    assert np.allclose(np.median(stds, axis=0), np.sqrt(np.diag(bound)), rtol=0.05)


def test_averaged_poses_are_weighted_by_their_scans():
    rng = np.random.default_rng(5)
    truth = perturbed_truth(rng)
    R = poses(60, rng, truth)
    counts = np.where(np.arange(60) % 2 == 0, 1, 16)
    one = implicit.cramer_rao(R, truth, PAPER7.tie_matrix, noise_volts=0.04)
    many = implicit.cramer_rao(
        R, truth, PAPER7.tie_matrix, noise_volts=0.04, scans_per_pose=np.full(60, 4)
    )
    assert np.allclose(many, one / 4)
    mixed = implicit.cramer_rao(
        R, truth, PAPER7.tie_matrix, noise_volts=0.04, scans_per_pose=counts
    )
    clean = implicit.predicted_volts(R, truth)
    V = clean + rng.normal(0.0, 0.04, clean.shape) / np.sqrt(counts)[:, None]
    res = identify(V, PAPER7, NOMINAL, method="ml", scans_per_pose=counts)
    # the noise of one scan is estimated from the weighted misfit; its std follows the bound
    assert 0.025 < res.sigma_volts < 0.055
    # (at the estimate rather than the truth: within a few per cent)
    assert np.allclose(res.std, np.sqrt(np.diag(mixed)) * res.sigma_volts / 0.04, rtol=0.04)


def test_selection_designs_on_the_ml_information():
    ps = simulate_poses(300, seed=6)
    cand = ml_candidates(ps.volts, PAPER7, ps.truth)
    assert cand.jacobian.shape == (300, 1, 7) and cand.usable.all()
    sel = select_poses(cand.jacobian, 40, information=cand.information)
    assert sel.upper_bound is not None and sel.min_singular <= sel.upper_bound * (1 + 1e-9)
    assert sel.min_singular >= 0.8 * sel.upper_bound  # close to the certified optimum
    # the rows are the information: their sum of squares inverts the bound (unit noise)
    idx = sel.indices
    rows = cand.information[idx, 0]
    bound = implicit.cramer_rao(
        implicit.start_rotations(ps.volts[idx], ps.truth)[0], ps.truth, PAPER7.tie_matrix,
        noise_volts=1.0,
    )  # fmt: skip
    assert np.allclose(rows.T @ rows, np.linalg.inv(bound), rtol=1e-8)
    # a set chosen on it beats a random one of the same size
    rand = np.random.default_rng(0).choice(300, 40, replace=False)
    info_rand = cand.information[rand, 0]
    assert np.linalg.eigvalsh(rows.T @ rows)[0] > 2 * np.linalg.eigvalsh(info_rand.T @ info_rand)[0]


@pytest.mark.slow
def test_ml_is_the_default_and_beats_the_paper_on_the_same_poses():
    errs = {"ml": [], "paper": []}
    for seed in range(6):
        ps = simulate_poses(450, seed=100 + seed)
        cal = calibrate(ps.volts, PAPER7, NOMINAL)
        assert cal.identification.method == "ml"
        idx = cal.selection.indices
        bound = np.sqrt(np.diag(implicit.cramer_rao(
            ps.rotations[idx], ps.truth, PAPER7.tie_matrix, noise_volts=0.04
        )))  # fmt: skip
        paper = identify(ps.volts[idx], PAPER7, NOMINAL, method="paper")
        for name, res in (("ml", cal.identification), ("paper", paper)):
            errs[name].append(
                (PAPER7.free_values(res.params) - PAPER7.free_values(ps.truth)) / bound
            )
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errs.items()}
    assert rms["ml"] < 1.4 and rms["ml"] < rms["paper"], rms


def test_bad_input_is_named():
    ps = simulate_poses(30, seed=7)
    with pytest.raises(InputError, match="unknown method 'lsq'"):
        identify(ps.volts, PAPER7, method="lsq")
    with pytest.raises(InputError, match="unknown method"):
        calibrate(ps.volts, PAPER7, method="ML")
    with pytest.raises(InputError, match="scans_per_pose must be 30 positive counts"):
        identify(ps.volts, PAPER7, scans_per_pose=np.ones(29))
    with pytest.raises(InputError, match="scans_per_pose must be 30 positive counts"):
        identify(ps.volts, PAPER7, scans_per_pose=np.zeros(30))
    with pytest.raises(InputError, match="noise_volts must be positive"):
        identify(ps.volts, PAPER7, noise_volts=-0.04)
    with pytest.raises(InputError, match="one count per pose"):
        calibrate(ps.volts, PAPER7, scans_per_pose=np.ones(3))
    with pytest.raises(InputError, match="NaN"):
        V = ps.volts.copy()
        V[3, 1] = np.nan
        identify(V, PAPER7, method="ml")
    with pytest.raises(InputError, match="cannot identify 7"):
        identify(ps.volts[:5], PAPER7, method="ml")
    with pytest.raises(InputError, match="not orthonormal"):
        implicit.cramer_rao(2 * ps.rotations, ps.truth, PAPER7.tie_matrix, noise_volts=0.04)


def dense_jacobian(Jp, Jr, w):
    """The whitened residuals' Jacobian (4 m, n + 3 m) over all unknowns: the free
    parameters, then each pose's rotation (left increments)."""
    m, n = Jp.shape[0], Jp.shape[2]
    J = np.zeros((4 * m, n + 3 * m))
    J[:, :n] = (-Jp * w[..., None]).reshape(4 * m, n)
    for k in range(m):
        J[4 * k : 4 * k + 4, n + 3 * k : n + 3 * k + 3] = -Jr[k] * w[k][:, None]
    return J


def test_the_eliminated_fit_is_the_least_squares_solution_of_all_unknowns():
    """Levenberg-Marquardt with the pose blocks eliminated ends where a dense solver of all
    unknowns at once (scipy's, on the same residuals, its Jacobian by finite differences)
    ends, from rotations up to 0.3 rad off: the same misfit, the same parameters and
    rotations to a small fraction of their standard errors; there the gradient over all
    unknowns vanishes; near the solution it takes Gauss-Newton's few iterations. From
    anywhere, its misfit never rises."""
    rng = np.random.default_rng(9)
    truth = perturbed_truth(rng)
    m, T = 15, PAPER7.tie_matrix
    n = T.shape[1]
    R = poses(m, rng, truth)
    V = implicit.predicted_volts(R, truth) + rng.normal(0.0, 0.04, (m, 4))
    w = rng.uniform(5.0, 30.0, (m, 4))

    def residuals(z):  # the free parameters' offsets from NOMINAL, the rotations' from R
        Rz = Rotation.from_rotvec(z[n:].reshape(m, 3)).as_matrix() @ R
        return ((V - implicit.predicted_volts(Rz, NOMINAL + T @ z[:n])) * w).ravel()

    ls = least_squares(residuals, np.zeros(n + 3 * m), method="lm", xtol=1e-15, ftol=1e-15,
                       gtol=1e-15)  # fmt: skip
    sd = np.sqrt(np.diag(np.linalg.inv(ls.jac.T @ ls.jac)))
    R_ls = Rotation.from_rotvec(ls.x[n:].reshape(m, 3)).as_matrix() @ R
    for size, seed in ((0.02, 0), (0.1, 1), (0.3, 2), (0.6, 0), (0.6, 1), (0.6, 2)):
        turned = Rotation.from_rotvec(np.random.default_rng(seed).normal(0.0, size, (m, 3)))
        history = []
        p, Rfit, iterations, converged, message, lin = implicit.fit_linearised(
            V, w, turned.as_matrix() @ R, T, NOMINAL, history=history
        )
        assert all(b <= a for a, b in itertools.pairwise(history)), (size, seed)
        assert len(history) <= iterations + 1
        x = np.linalg.lstsq(T, p - NOMINAL, rcond=None)[0]
        assert np.allclose(NOMINAL + T @ x, p, rtol=0, atol=1e-12)  # fixed parameters kept
        assert np.allclose(Rfit @ np.swapaxes(Rfit, 1, 2), np.eye(3), atol=1e-12)
        # the problem linearised at the end is the one at the end
        vhat, Jp, Jr = implicit.model_jacobians(Rfit, p, T)
        r = (V - vhat) * w
        assert np.allclose(lin.r.T, r, rtol=0, atol=1e-12)
        assert lin.cost == pytest.approx(np.sum(r**2), rel=1e-12)
        assert history[-1] == pytest.approx(lin.cost, rel=1e-12)
        assert converged, message
        if size > 0.3:
            continue  # far off: perhaps another minimum
        assert iterations <= 15
        assert lin.cost == pytest.approx(2 * ls.cost, rel=1e-7)
        assert np.all(np.abs(x - ls.x[:n]) <= 1e-3 * sd[:n])
        turn = Rotation.from_matrix(Rfit @ np.swapaxes(R_ls, 1, 2)).magnitude()
        assert np.all(turn <= 1e-3 * np.linalg.norm(sd[n:].reshape(m, 3), axis=1))
        # stationary: the gradient over every unknown, against the size of its column
        J = dense_jacobian(Jp, Jr, w)
        g = J.T @ r.ravel()
        assert np.all(np.abs(g) <= 1e-4 * np.linalg.norm(J, axis=0) * np.linalg.norm(r))


def test_information_rows_are_the_svd_loop_direction():
    rng = np.random.default_rng(9)
    truth = perturbed_truth(rng)
    m, T = 15, PAPER7.tie_matrix
    R = poses(m, rng, truth)
    V = implicit.predicted_volts(R, truth) + rng.normal(0.0, 0.04, (m, 4))
    w = rng.uniform(5.0, 30.0, (m, 4))
    lin = implicit.linearise(V, w, R, NOMINAL, T)
    vhat, Jp, Jr = implicit.model_jacobians(R, NOMINAL, T)
    assert np.allclose(lin.r.T, (V - vhat) * w, rtol=1e-12, atol=1e-12)
    # the information rows: the SVD's loop direction, up to each row's sign
    U = np.linalg.svd(Jr * w[..., None], full_matrices=True)[0][:, :, 3]
    expected = np.einsum("mrn,mr->mn", Jp * w[..., None], U)
    got = lin.information()
    sign = np.sign(np.einsum("mn,mn->m", expected, got))
    assert np.allclose(
        got * sign[:, None], expected, rtol=1e-10, atol=1e-12 * np.abs(expected).max()
    )
    rows = implicit.weighted_information(R, NOMINAL, T, w)
    assert np.allclose(rows.T @ rows, expected.T @ expected, rtol=1e-10)
