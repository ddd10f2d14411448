"""The ``loopcal`` command line."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from calibration.errors import CalibrationError
from calibration.observability import analyse_identifiability
from calibration.parameters import NOMINAL, ParameterModel
from calibration.pipeline import calibrate
from calibration.selection import candidate_jacobian
from calibration.simulate import perturbed_truth, simulate_poses
from simulator import run as simulate_run


def _model(args: argparse.Namespace) -> ParameterModel:
    return ParameterModel.parse(args.free, args.ties or ())


def _add_model_options(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--free",
        default="paper7",
        help="free parameters: a preset (paper7, offsets, all, d01..d04) or names, "
        "e.g. 'd03' or 'd01,d02,A1x' (default: paper7)",
    )
    p.add_argument(
        "--ties",
        default=None,
        help="ties for a custom free set, e.g. 'A3x=-A2x,A4x=-A1x' (presets bring their own)",
    )


def cmd_demo(args: argparse.Namespace) -> int:
    """Calibrate a simulated shoulder joint whose LVDT offsets were lost."""
    model = _model(args)
    rng = np.random.default_rng(args.seed)
    truth = perturbed_truth(rng, offsets_mm=args.offset_error, model=model)
    print(
        f"Simulated mechanism: free parameters moved from the blueprint (offsets by up to "
        f"{args.offset_error} mm); {model.describe()}"
    )
    t0 = time.perf_counter()
    ps = simulate_poses(args.poses, truth=truth, seed=rng, noise_volts=args.noise_mv / 1000)
    print(
        f"Recorded {len(ps)} poses while the plate was moved by hand "
        f"(noise {args.noise_mv:g} mV, 12-bit codes)."
    )
    cal = calibrate(ps.volts, model, NOMINAL, n_select=args.select)
    sel, res = cal.selection, cal.identification
    print(
        f"Selected {len(sel.indices)} poses of {len(ps)} in {cal.rounds} round(s):"
        f" s_min {sel.indices_own.min_singular:.3g}, condition {sel.indices_own.condition:.3g}"
        f" (own scaling); s_min {sel.min_singular:.4g} = {100 * sel.bound_ratio:.1f} % of the"
        f" certified bound {sel.upper_bound:.4g} (pool scaling)."
    )
    dt = time.perf_counter() - t0
    print()
    print(res.table(truth))
    for problem in res.problems():
        print(f"WARNING: {problem}")
    print()
    offs = res.params[16:20]
    print("New sensor offsets: " + ", ".join(f"d0{i + 1} = {v:.3f} mm" for i, v in enumerate(offs)))
    print(f"Done in {dt:.2f} s.")
    return 0 if not res.problems() else 1


def cmd_observability(args: argparse.Namespace) -> int:
    """Which parameters a pose set can identify (the paper's steps a-c)."""
    model = _model(args)
    ps = simulate_poses(args.poses, seed=args.seed, noise_volts=0.0, quantize=False)
    cand = candidate_jacobian(ps.volts, model, ps.truth)
    report = analyse_identifiability(
        cand.jacobian[cand.usable], model, condition_limit=args.condition_limit
    )
    print(report.summary())
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="loopcal",
        description="Closed-loop field calibration of the redundant shoulder joint.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help=cmd_demo.__doc__, description=cmd_demo.__doc__)
    _add_model_options(demo)
    demo.add_argument("--poses", type=int, default=450, help="poses recorded (default 450)")
    demo.add_argument("--select", type=int, default=50, help="poses selected (default 50)")
    demo.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    demo.add_argument("--noise-mv", type=float, default=40.0, help="sensor noise, mV (40)")
    demo.add_argument(
        "--offset-error", type=float, default=3.0, help="how far offsets moved, mm (3)"
    )
    demo.set_defaults(func=cmd_demo)

    obs = sub.add_parser(
        "observability", help=cmd_observability.__doc__, description=cmd_observability.__doc__
    )
    _add_model_options(obs)
    obs.add_argument("--poses", type=int, default=450)
    obs.add_argument("--seed", type=int, default=1)
    obs.add_argument("--condition-limit", type=float, default=1000.0)
    obs.set_defaults(func=cmd_observability)

    sim = sub.add_parser(
        "simulate",
        help="serve an emulated LDQ-412 driven by a simulated shoulder joint",
        description=simulate_run.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    simulate_run.add_arguments(sim)
    sim.set_defaults(func=simulate_run.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except CalibrationError as exc:
        print(f"loopcal: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
