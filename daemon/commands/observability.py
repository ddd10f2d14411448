"""``loopcal observability``: which parameters a pose set can identify (the paper's steps
a-c), on simulated poses spread over the workspace."""

from __future__ import annotations

import argparse

from loopcal.calibration.observability import analyse_identifiability
from loopcal.calibration.selection import candidate_jacobian
from loopcal.calibration.simulate import simulate_poses

from .model_options import add_model_options, model_from_args


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_options(p)
    p.add_argument("--poses", type=int, default=450)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--condition-limit", type=float, default=1000.0)


def run(args: argparse.Namespace) -> int:
    model = model_from_args(args)
    ps = simulate_poses(args.poses, seed=args.seed, noise_volts=0.0, quantize=False)
    cand = candidate_jacobian(ps.volts, model, ps.truth)
    report = analyse_identifiability(
        cand.jacobian[cand.usable], model, condition_limit=args.condition_limit
    )
    print(report.summary())
    return 0
