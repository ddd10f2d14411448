"""The simulated session's options, one definition with one set of defaults for every command
that simulates a technician's hand: ``loopcal simulate``, ``loopcal demo`` and ``loopcal
observability --session``.

The defaults are the session the live guidance asks for, as ``loopcal demo`` has always
run it: seed 1, a pause of 0.8 to 1.5 s at each position, a twist about the plate's own
axis every other move, 40 mV of sensor noise, offsets up to 3 mm off the blueprint.
"""

from __future__ import annotations

import argparse
import math

from loopcal.calibration.defaults import NOISE_VOLTS

#: the random seed of the motion, the noise and the true parameters
SEED = 1
#: s, (min, max) a technician's hand holds each position: about a second
PAUSE_S = (0.8, 1.5)
#: every N-th move twists the plate about its own axis (2: every other, as the guidance asks)
TWIST_EVERY = 2
#: mV rms of sensor noise
NOISE_MV = 1000 * NOISE_VOLTS
#: mm: the true offsets differ from the blueprint by up to this (refitted LVDTs)
OFFSET_ERROR_MM = 3.0


class SimulationError(ValueError):
    """A simulation refused before it runs: an option's value, a truth file that cannot be
    written, servers that cannot start. The message names the option or file.

    ``loopcal simulate`` lets it through to the command line's one error path (``loopcal
    simulate: error: MESSAGE``, exit status 2), which knows it as bad input.
    """


def pause_argument(text: str) -> tuple[float, float]:
    """An argparse type: ``MIN,MAX`` seconds, ``0 < MIN <= MAX``.

    Parameters
    ----------
    text : str
        E.g. ``0.8,1.5``.

    Returns
    -------
    tuple of 2 float
        (min, max), s.

    Raises
    ------
    argparse.ArgumentTypeError
        If it is not two numbers, or not ``0 < MIN <= MAX``.
    """
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give MIN,MAX seconds, e.g. 0.8,1.5") from None
    if not 0 < lo <= hi < math.inf:
        raise argparse.ArgumentTypeError(f"{text!r}: need 0 < MIN <= MAX")
    return lo, hi


def add_simulation_options(p: argparse.ArgumentParser, *, truth: bool = True,
                           what: str = "", noise_what: str = "") -> None:  # fmt: skip
    """Add the simulated session's options: ``--seed``, ``--pause``, ``--twist-every``,
    ``--noise-mv`` and (``truth``) ``--offset-error``, with this module's defaults.

    Parameters
    ----------
    p : argparse.ArgumentParser
        The command's parser.
    truth : bool, default True
        Add ``--offset-error`` (for a command whose mechanism's true parameters are
        drawn from the seed).
    what : str, default ""
        Said first in the help of the options that shape the hand's motion (``--pause``,
        ``--twist-every``), e.g. ``"with --scenario hand: "``.
    noise_what : str, default ""
        Said first in ``--noise-mv``'s help, e.g. ``"with --session: "``.
    """
    p.add_argument("--seed", type=int, default=SEED,
                   help="random seed of the motion"
                        + (", the noise and the true parameters" if truth else " and the noise")
                        + f" (default {SEED})")  # fmt: skip
    p.add_argument("--pause", type=pause_argument, default=PAUSE_S, metavar="MIN,MAX",
                   help=f"{what}seconds the hand holds each position "
                        f"(default {PAUSE_S[0]:g},{PAUSE_S[1]:g})")  # fmt: skip
    p.add_argument("--twist-every", type=int, default=TWIST_EVERY, metavar="N",
                   help=f"{what}every N-th move twists the plate about its own axis, as the "
                        f"live guidance asks (default {TWIST_EVERY}; 0: never)")  # fmt: skip
    p.add_argument("--noise-mv", type=float, default=NOISE_MV, metavar="MV",
                   help=f"{noise_what}sensor noise, mV rms (default {NOISE_MV:g})")  # fmt: skip
    if truth:
        p.add_argument("--offset-error", type=float, default=OFFSET_ERROR_MM, metavar="MM",
                       help="the true offsets differ from the blueprint by up to this, mm "
                            f"(default {OFFSET_ERROR_MM:g})")  # fmt: skip


def check_simulation_options(args: argparse.Namespace) -> None:
    """Check the values :func:`add_simulation_options` parsed.

    Parameters
    ----------
    args : argparse.Namespace
        The command's arguments.

    Raises
    ------
    ValueError
        Naming the option and the value: ``--twist-every`` under 0, ``--noise-mv``
        negative or not finite, ``--offset-error`` (where there is one) negative or not
        finite.
    """
    if args.twist_every < 0:
        raise ValueError(f"--twist-every must be 0 or more moves, got {args.twist_every}")
    if not (math.isfinite(args.noise_mv) and args.noise_mv >= 0):
        raise ValueError(f"--noise-mv must not be negative, got {args.noise_mv:g}")
    error = getattr(args, "offset_error", 0.0)
    if not (math.isfinite(error) and error >= 0):
        raise ValueError(f"--offset-error must be 0 or more mm, got {error:g}")
