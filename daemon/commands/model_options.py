"""The ``--free`` / ``--ties`` options shared by the commands that identify parameters."""

from __future__ import annotations

import argparse

from loopcal.calibration.parameters import ParameterModel


def add_model_options(p: argparse.ArgumentParser, *, default: str | None = "paper7") -> None:
    p.add_argument(
        "--free",
        default=default,
        help="free parameters: a preset (paper7, offsets, all, d01..d04) or names, "
        f"e.g. 'd03' or 'd01,d02,A1x' (default: {default})",
    )
    p.add_argument(
        "--ties",
        default=None,
        help="ties for a custom free set, e.g. 'A3x=-A2x,A4x=-A1x' (presets bring their own)",
    )


def model_from_args(args: argparse.Namespace) -> ParameterModel:
    return ParameterModel.parse(args.free, args.ties or ())
