"""The options shared by the commands that identify parameters: ``--free`` and ``--ties``
(one syntax in calibrate, demo and observability), and ``--select``.

Their defaults come from :mod:`loopcal.calibration.defaults`, which imports nothing: adding
these options does not import numpy (``--help`` prints at once); the parameter model is
built, and imported, only by :func:`model_from_args`.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from loopcal.calibration.defaults import DEFAULT_FREE, DEFAULT_N_SELECT

if TYPE_CHECKING:
    from loopcal.calibration.parameters import ParameterModel

FREE_HELP = ("free parameters: a preset (paper7, offsets, all, d01..d04) or names separated by "
             "commas, e.g. d03 or d01,d02,A1x")  # fmt: skip


def add_model_options(p: argparse.ArgumentParser, *, default: str | None = DEFAULT_FREE,
                      default_text: str | None = None) -> None:  # fmt: skip
    """``--free NAMES`` (one value; ``default`` None: the caller decides, as
    ``default_text`` says) and ``--ties``."""
    p.add_argument("--free", default=default, metavar="NAMES",
                   help=f"{FREE_HELP} (default: {default_text or default})")  # fmt: skip
    p.add_argument("--ties", default=None, metavar="TIES",
                   help="ties for a custom free set, e.g. A3x=-A2x,A4x=-A1x (presets bring "
                        "their own)")  # fmt: skip


def add_select_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--select", type=int, default=DEFAULT_N_SELECT, metavar="N",
                   help=f"poses selected for the fit (default {DEFAULT_N_SELECT})")  # fmt: skip


def model_from_args(args: argparse.Namespace) -> ParameterModel:
    from loopcal.calibration.parameters import ParameterModel

    return ParameterModel.parse(args.free, args.ties or ())
