"""``loopcal observability``: which parameters a pose set can identify (the paper's steps
a-c), on simulated poses spread over the workspace, or (``--session SECONDS``) on every scan
of a simulated technician's hand session, as the worker's maximum-likelihood fit sees them.

Exit status: 0 every chosen parameter is observable, 1 some are not (the weak directions
and a free set that reaches the condition limit are shown), 2 bad input."""

from __future__ import annotations

import argparse
import json
import math
from typing import TYPE_CHECKING

from loopcal.calibration.defaults import CONDITION_OK
from loopcal.simulator.options import add_simulation_options, check_simulation_options

from ..arguments import duration_argument
from .errors import CommandError
from .model_options import add_model_options, model_from_args
from .option_rules import note_given, refuse_unless

if TYPE_CHECKING:
    import numpy as np

#: the simulation options that shape a --session's hand and noise: nothing without it
SESSION_OPTIONS = ("--pause", "--twist-every", "--noise-mv")


def add_arguments(p: argparse.ArgumentParser) -> None:
    note_given(p)
    add_model_options(p)
    p.add_argument("--poses", type=int, default=450, metavar="N",
                   help="not with --session: simulated still poses spread over the workspace "
                        "(default 450)")  # fmt: skip
    p.add_argument("--session", type=duration_argument, default=None, metavar="D",
                   help="judge every scan of a simulated hand session this long (seconds, or "
                        "90s, 2m; 20 Hz; "
                        "its pauses, twists and noise as --pause, --twist-every and "
                        "--noise-mv say) by its maximum-likelihood information, as the worker "
                        "fits it, instead of --poses still poses by the paper's "
                        "Jacobian")  # fmt: skip
    add_simulation_options(p, truth=False, what="with --session: ", noise_what="with --session: ")
    p.add_argument("--condition-limit", type=float, default=CONDITION_OK, metavar="C",
                   help="the largest condition number a free set may have "
                        f"(default {CONDITION_OK:g})")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help="one JSON object on stdout: indices, status and relative std per "
                        "parameter, weak directions, the suggested free set")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    if args.poses < 1:
        raise CommandError(f"--poses {args.poses}: at least 1")
    if not (math.isfinite(args.condition_limit) and args.condition_limit >= 1):
        raise CommandError(f"--condition-limit {args.condition_limit:g}: a condition number, "
                           "1 or more")
    try:
        check_simulation_options(args)
    except ValueError as exc:  # the option and its value, named
        raise CommandError(exc) from None
    session = args.session is not None  # a bad value is named first, then where it applies
    refuse_unless(args, not session, "not with --session",
                  "a session's scans are judged instead of --poses still poses", "--poses")
    refuse_unless(args, session, "only with --session",
                  "the still poses spread over the workspace are noise-free and placed, not "
                  "moved by a hand", *SESSION_OPTIONS)  # fmt: skip
    from loopcal.calibration.observability import analyse_identifiability
    from loopcal.calibration.selection import candidate_jacobian
    from loopcal.calibration.simulate import simulate_poses

    model = model_from_args(args)
    if session:
        J = _session_information(args, model)
    else:
        ps = simulate_poses(args.poses, seed=args.seed, noise_volts=0.0, quantize=False)
        cand = candidate_jacobian(ps.volts, model, ps.truth)
        J = cand.jacobian[cand.usable]
    report = analyse_identifiability(J, model, condition_limit=args.condition_limit)
    if args.json:
        def num(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        print(json.dumps({
            "free": list(model.free),
            "ties": [{"follower": t.follower, "leader": t.leader, "ratio": t.ratio}
                     for t in model.ties],
            "poses": report.indices.n_poses,
            "indices": {k: num(v) for k, v in report.indices.as_dict().items()},
            "status": report.status,
            "relative_std": {k: num(v) for k, v in report.relative_std.items()},
            "weak_directions": [
                {"weights": c.weights, "singular_value": num(c.singular_value),
                 "condition": num(c.condition)} for c in report.combinations],
            "suggested_free": list(report.suggestion.free) if report.suggestion else None,
            "observable": report.observable,
        }, indent=1))  # fmt: skip
    else:
        print(report.summary())
    return 0 if report.observable else 1


def _session_information(args: argparse.Namespace, model) -> np.ndarray:
    """The maximum-likelihood information rows (m, 1, n) of every scan of a simulated hand
    session ``args.session`` s long (the reference mechanism, moved as
    :class:`loopcal.simulator.scenarios.HandMoves` does with the options' seed, pauses and
    twists, 20 Hz, its true rotations at each scan's instant, weighed by ``--noise-mv``)."""
    seconds = args.session
    if not 1 <= seconds <= 86400:
        raise CommandError(f"--session {seconds:g} s: between 1 s and a day")
    if not args.noise_mv > 0:
        raise CommandError(f"--session needs noise to weigh the scans: --noise-mv "
                           f"{args.noise_mv:g}")
    import numpy as np

    from loopcal.calibration import implicit
    from loopcal.calibration.parameters import NOMINAL
    from loopcal.simulator.scenarios import HandMoves

    t = np.arange(round(seconds * 20)) / 20.0
    R = HandMoves(args.seed, params=NOMINAL, pause_s=args.pause,
                  twist_every=args.twist_every).rotation(t)  # fmt: skip
    w = np.full((len(R), 4), 1000.0 / args.noise_mv)
    return implicit.weighted_information(R, NOMINAL, model.tie_matrix, w)[:, None, :]
