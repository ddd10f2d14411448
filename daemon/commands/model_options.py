"""The options shared by the commands that identify parameters: ``--free`` and ``--ties``
(one syntax in calibrate, demo and observability), and ``--select``.

Their defaults come from :mod:`loopcal.calibration.defaults`, which imports nothing: adding
these options does not import numpy (``--help`` prints at once); the parameter model is
built, and imported, only by :func:`model_from_args` and :func:`parse_model`.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from loopcal.calibration.defaults import DEFAULT_FREE, DEFAULT_N_SELECT

from .errors import CommandError

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
                   help="ties for a custom free set given by --free (names, not a preset: "
                        "presets bring their own), e.g. A3x=-A2x,A4x=-A1x")  # fmt: skip


def add_select_option(p: argparse.ArgumentParser) -> None:
    """``--select N``: how many still poses the paper's method selects (``--method paper``
    only; the default method fits every scan and selects none)."""
    p.add_argument("--select", type=int, default=DEFAULT_N_SELECT, metavar="N",
                   help=f"with --method paper: still poses selected for the fit "
                        f"(default {DEFAULT_N_SELECT})")  # fmt: skip


def parse_model(free: str, ties: str | None) -> ParameterModel:
    """The parameter model of a ``--free`` and a ``--ties`` value.

    Raises CommandError for ties with a preset (``--free paper7`` brings its own ties, and
    ``--ties`` would be ignored or misread as naming a parameter ``paper7``); a bad name or
    tie raises :class:`~loopcal.calibration.errors.ParameterError` (bad input too)."""
    from loopcal.calibration.parameters import PRESETS, ParameterModel

    if ties and free.strip() in PRESETS:
        raise CommandError(f"--ties goes with a custom free set (--free NAMES), not the preset "
                           f"{free.strip()}, which brings its own ties")  # fmt: skip
    return ParameterModel.parse(free, ties or ())


def model_from_args(args: argparse.Namespace) -> ParameterModel:
    """The parameter model of the parsed ``--free`` and ``--ties`` (:func:`parse_model`)."""
    return parse_model(args.free, args.ties)
