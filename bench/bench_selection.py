"""Pose selection: choose 50 of 10,000 candidate poses for the paper's 7 parameters.

    python -m bench.bench_selection [--repeats 5]

Prints the time, the chosen set's minimum singular value as a fraction of the certified
upper bound (see calibration/selection.py: for any trace-one Z >= 0, lambda_min of every
50-subset is at most the sum of the 50 largest <Z, A_k>; the relaxation's best Z is used),
against random choice, and the paper's setting (50 of 450). Values are on the pool's column
scaling, for the noise-whitened information the selection designs on, and for the paper's
unweighted Jacobian of the chosen set.
"""

from __future__ import annotations

import numpy as np

from bench._timing import median_time, repeats_parser
from loopcal.calibration.observability import column_scales, observability_indices
from loopcal.calibration.parameters import NOMINAL, PAPER7
from loopcal.calibration.selection import candidate_jacobian, select_poses
from loopcal.calibration.simulate import simulate_poses


def run(n_candidates: int, k: int, repeats: int, seed: int) -> None:
    ps = simulate_poses(n_candidates, seed=seed)
    t_prep, cand = median_time(lambda: candidate_jacobian(ps.volts, PAPER7, NOMINAL), repeats)
    t_sel, sel = median_time(
        lambda: select_poses(cand.jacobian, k, information=cand.information), repeats
    )
    info = cand.information
    h = column_scales(info)
    rng = np.random.default_rng(seed)
    pool = np.flatnonzero(cand.usable)
    random = [
        observability_indices(info[rng.choice(pool, k, replace=False)], h).min_singular
        for _ in range(200)
    ]
    hj = column_scales(cand.jacobian)
    paper_random = [
        observability_indices(cand.jacobian[rng.choice(pool, k, replace=False)], hj).min_singular
        for _ in range(200)
    ]
    paper_sel = observability_indices(cand.jacobian[sel.indices], hj).min_singular
    print(f"select {k} of {n_candidates} candidates ({len(pool)} usable)")
    print(
        f"  time: selection {1000 * t_sel:.0f} ms (median of {repeats}), "
        f"candidate Jacobian {1000 * t_prep:.0f} ms; target < 1 s"
    )
    print(
        f"  s_min chosen {sel.min_singular:.4g}, certified bound {sel.upper_bound:.4g}: "
        f"ratio {sel.bound_ratio:.3f} (target >= 0.9); condition {sel.condition:.3g}"
    )
    print(
        f"  random {k}: median s_min {np.median(random):.4g}, best of 200 "
        f"{np.max(random):.4g}; chosen / median random = "
        f"{sel.min_singular / np.median(random):.1f} x"
    )
    print(
        f"  paper's unweighted index (pool scale): chosen {paper_sel:.4g}, random median "
        f"{np.median(paper_random):.4g}; own scaling: s_min {sel.indices_own.min_singular:.3g},"
        f" condition {sel.indices_own.condition:.3g}; swaps {sel.swaps}, passes {sel.passes}"
    )
    print()


def main() -> None:
    args = repeats_parser(__doc__).parse_args()
    run(10_000, 50, args.repeats, seed=3)
    run(450, 50, args.repeats, seed=3)  # the paper's setting


if __name__ == "__main__":
    main()
