"""The ``loopcal`` command line."""

from __future__ import annotations

import argparse
import sys

from calibration.errors import CalibrationError
from calibration.observability import analyse_identifiability
from calibration.parameters import ParameterModel
from calibration.selection import candidate_jacobian
from calibration.simulate import simulate_poses
from simulator import run as simulate_run

from . import demo


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
    """Calibrate a simulated shoulder joint whose LVDT offsets were lost, through its
    emulated DAQ."""
    return demo.run(args, _model(args))


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

    demo_p = sub.add_parser("demo", help=cmd_demo.__doc__, description=cmd_demo.__doc__)
    _add_model_options(demo_p)
    demo.add_arguments(demo_p)
    demo_p.set_defaults(func=cmd_demo)

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
    except (CalibrationError, ValueError) as exc:
        print(f"loopcal: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
