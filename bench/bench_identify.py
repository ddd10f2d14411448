"""Identification speed: loopcal's analytic-Jacobian LM against scipy.optimize.least_squares
with its default finite-difference Jacobian, on the same vectorised residuals and data, and
loopcal's time against the number of poses.

    python -m bench.bench_identify [--repeats 5]

Both solvers get the same poses and the same branch references, so they minimise the same
function. scipy starts at the nominal parameters, as loopcal does, and its tolerances are
tightened (1e-12) so that it goes as far as its finite-difference gradient lets it.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from bench._timing import median_time, repeats_parser
from loopcal.calibration.identify import _levenberg_marquardt, identify
from loopcal.calibration.parameters import NOMINAL, PAPER7
from loopcal.calibration.residuals import loop_residuals, reference_points
from loopcal.calibration.simulate import simulate_poses


def scipy_fit(
    volts: np.ndarray, ref: np.ndarray, jac: str = "2-point", diff_step: float | None = None
) -> np.ndarray:
    """scipy's least_squares (TRF) on the same residuals, finite-difference Jacobian."""
    model = PAPER7

    def fun(x: np.ndarray) -> np.ndarray:
        p = model.expand(x, NOMINAL)
        return loop_residuals(p, volts, ref, jacobian=False).residuals.reshape(-1)

    x0 = model.free_values(NOMINAL)
    sol = least_squares(fun, x0, jac=jac, ftol=1e-12, xtol=1e-12, gtol=1e-12, diff_step=diff_step)
    return model.expand(sol.x, NOMINAL)


def fit_fixed(V: np.ndarray, ref: np.ndarray) -> tuple[np.ndarray, int, bool, str]:
    """The bare solver inside :func:`identify` (paper's method): Levenberg-Marquardt on
    fixed poses with fixed branch references from NOMINAL, no pose screening, no
    covariance: what scipy's least_squares is given here, like for like. A private function
    of calibration.identify, measured as such."""
    model = PAPER7
    p, _, _, it, converged, message = _levenberg_marquardt(
        V, ref, model, NOMINAL, model.free_values(NOMINAL), NOMINAL, 100, 1e-8, 1e-12, 50.0, []
    )
    return p, it, converged, message


def cost(p: np.ndarray, volts: np.ndarray, ref: np.ndarray) -> float:
    f = loop_residuals(p, volts, ref, jacobian=False).residuals.reshape(-1)
    return float(f @ f)


def gradient_norm(p: np.ndarray, volts: np.ndarray, ref: np.ndarray) -> float:
    """|J^T f| / (|J| |f|) with the analytic Jacobian: zero at the exact minimum."""
    r = loop_residuals(p, volts, ref, directions=PAPER7.tie_matrix)
    f = r.residuals.reshape(-1)
    J = r.jacobian.reshape(len(f), -1)
    return float(np.linalg.norm(J.T @ f) / (np.linalg.norm(J) * np.linalg.norm(f) + 1e-300))


def compare(label: str, noise_volts: float, repeats: int) -> None:
    ps = simulate_poses(450, seed=1, noise_volts=noise_volts, quantize=noise_volts > 0)
    t_full, res = median_time(lambda: identify(ps.volts, PAPER7, NOMINAL), repeats)
    V = ps.volts[res.used]
    ref = reference_points(V, res.params)
    # like for like: the same poses, branch references and start for both solvers
    t_ours, (p_ours, iters, _, _) = median_time(lambda: fit_fixed(V, ref), repeats)
    t_2p, p_2p = median_time(lambda: scipy_fit(V, ref), repeats)
    t_3p, p_3p = median_time(lambda: scipy_fit(V, ref, "3-point"), repeats)
    t_fine, p_fine = median_time(lambda: scipy_fit(V, ref, diff_step=1e-9), repeats)
    idx = PAPER7.free_index

    def dist(p: np.ndarray) -> str:
        return f"{np.abs(p_ours - p)[idx].max():.2e} mm"

    def above(p: np.ndarray) -> str:
        return f"{cost(p, V, ref) - cost(p_ours, V, ref):.1e}"

    print(f"identification from 450 poses, paper's 7 parameters, {label}")
    print(
        f"  loopcal identify(), end to end  : {1000 * t_full:7.1f} ms (median of {repeats}; "
        "pose screening, branch references, covariance)"
    )
    print(
        f"  loopcal LM, analytic Jacobian   : {1000 * t_ours:7.1f} ms ({iters} iterations; "
        "scipy gets the same poses, references and start)"
    )
    for name, t, p in (
        ("2-point (default)", t_2p, p_2p),
        ("3-point", t_3p, p_3p),
        ("2-point, step 1e-9", t_fine, p_fine),
    ):
        print(
            f"  scipy {name:<20}      : {1000 * t:7.1f} ms  speed-up {t / t_ours:4.1f} x;"
            f" answer {dist(p)} from loopcal's; cost above it {above(p)} mm^4"
        )
    print(f"  loopcal LM vs identify()        : {dist(res.params)}")
    print(
        f"  relative gradient |J^T f|/|J||f|: loopcal {gradient_norm(p_ours, V, ref):.1e}, "
        f"scipy default {gradient_norm(p_2p, V, ref):.1e}"
    )
    print()


def main() -> None:
    args = repeats_parser(__doc__).parse_args()
    compare("40 mV noise", 0.040, args.repeats)
    compare("noise-free readings", 0.0, args.repeats)
    print("time against pose count (loopcal, 40 mV)")
    print(f"  {'poses':>6} {'median ms':>10} {'us/pose':>8} {'iterations':>10}")
    for n in (450, 1000, 2000, 5000, 10000):
        ps_n = simulate_poses(n, seed=2)
        t, r = median_time(lambda ps_n=ps_n: identify(ps_n.volts, PAPER7, NOMINAL), args.repeats)
        print(f"  {n:6d} {1000 * t:10.1f} {1e6 * t / n:8.1f} {r.iterations:10d}")


if __name__ == "__main__":
    main()
