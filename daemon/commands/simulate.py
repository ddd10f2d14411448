"""``loopcal simulate``: the emulated LDQ-412 driven by a simulated shoulder joint (the
command itself lives with the simulator: its options in :mod:`loopcal.simulator.arguments`,
its serving in :mod:`loopcal.simulator.run`; its ``--duration`` takes the command line's one
duration syntax)."""

from __future__ import annotations

import argparse

from loopcal.simulator.arguments import DESCRIPTION
from loopcal.simulator.arguments import add_arguments as simulator_arguments

from ..arguments import duration_argument

__all__ = ["DESCRIPTION", "add_arguments", "run"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    simulator_arguments(p, duration=duration_argument)


def run(args: argparse.Namespace) -> int:
    from loopcal.simulator.run import run as serve

    return serve(args)
