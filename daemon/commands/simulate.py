"""``loopcal simulate``: the emulated LDQ-412 driven by a simulated shoulder joint (the
command itself lives with the simulator: its options in :mod:`loopcal.simulator.arguments`,
its serving in :mod:`loopcal.simulator.run`; its ``--duration`` takes the command line's one
duration syntax)."""

from __future__ import annotations

import argparse

from loopcal.simulator.arguments import DESCRIPTION
from loopcal.simulator.arguments import add_arguments as simulator_arguments

from ..arguments import duration_argument
from .option_rules import note_given, refuse_unless

__all__ = ["DESCRIPTION", "add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    note_given(p)
    simulator_arguments(p, duration=duration_argument)


def run(args: argparse.Namespace) -> int:
    from loopcal.simulator.run import run as serve

    refuse_unless(args, args.scenario == "hand", "only with --scenario hand",
                  f"--scenario {args.scenario} moves the plate its own way",
                  "--pause", "--twist-every")  # fmt: skip

    return serve(args)
