"""Identification speed: loopcal's analytic-Jacobian LM against scipy.optimize.least_squares
with its default finite-difference Jacobian, on the same vectorised residuals and data, and
loopcal's time against the number of poses.

    python bench/bench_identify.py [--repeats 5]
"""

from __future__ import annotations

import argparse

import numpy as np
from _timing import median_time
from scipy.optimize import least_squares

from calibration.identify import identify
from calibration.parameters import NOMINAL, PAPER7
from calibration.residuals import loop_residuals, reference_points
from calibration.simulate import simulate_poses


def scipy_fit(volts: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """scipy's default least_squares (TRF, 2-point finite differences) on the same residuals;
    tolerances tightened so both solvers reach the same minimum."""
    model = PAPER7

    def fun(x: np.ndarray) -> np.ndarray:
        p = model.expand(x, NOMINAL)
        return loop_residuals(p, volts, ref, jacobian=False).residuals.reshape(-1)

    sol = least_squares(fun, model.free_values(NOMINAL), ftol=1e-12, xtol=1e-12, gtol=1e-12)
    return model.expand(sol.x, NOMINAL)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    ps = simulate_poses(450, seed=1)
    t_ours, res = median_time(lambda: identify(ps.volts, PAPER7, NOMINAL), args.repeats)
    # same poses, same branch references: the same objective for both solvers
    V = ps.volts[res.used]
    ref = reference_points(V, res.params)
    t_scipy, p_scipy = median_time(lambda: scipy_fit(V, ref), args.repeats)
    diff = np.abs(res.params - p_scipy)[PAPER7.free_index].max()
    print("identification from 450 poses, paper's 7 parameters, 40 mV noise")
    print(f"  loopcal LM, analytic Jacobian : {1000 * t_ours:8.1f} ms (median of {args.repeats})")
    print(f"  scipy least_squares, 2-point FD: {1000 * t_scipy:8.1f} ms")
    print(f"  speed-up                       : {t_scipy / t_ours:8.1f} x  (target >= 3)")
    print(f"  max |difference| of estimates  : {diff:.2e} mm  (target < 1e-6)")
    print()
    print("time against pose count (loopcal)")
    print(f"  {'poses':>6} {'median ms':>10} {'us/pose':>8} {'iterations':>10}")
    for n in (450, 1000, 2000, 5000, 10000):
        ps_n = simulate_poses(n, seed=2)
        t, r = median_time(lambda ps_n=ps_n: identify(ps_n.volts, PAPER7, NOMINAL), args.repeats)
        print(f"  {n:6d} {1000 * t:10.1f} {1e6 * t / n:8.1f} {r.iterations:10d}")


if __name__ == "__main__":
    main()
