"""How a command refuses: :class:`CommandError`, and the domain errors that mean bad input.

A command raises :class:`CommandError` (or lets one of :data:`BAD_INPUT` through);
``loopcal.daemon.cli.main`` alone prints it, ``loopcal CMD: error: MESSAGE``, and exits with
its status. Any other exception, a plain ``ValueError`` or ``TypeError`` included, is a bug
and stays a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from importlib.util import resolve_name


class CommandError(Exception):
    """A command's refusal: what is wrong, in words for the user, and the exit status.

    Parameters
    ----------
    message : str
        What is wrong, naming the option or file and the value. Several problems go one
        a line: each line is printed as an error of its own.
    status : int, default 2
        The exit status (2: bad input; 1 where the command's docs say so).
    """

    def __init__(self, message: object, status: int = 2) -> None:
        super().__init__(str(message))
        self.status = status


#: the domain errors that mean bad input, as (module, class; a module of daemon/ relative
#: to this package): a settings or controller config that is refused, a recording that
#: cannot be read, a module held by another process, a daemon that refuses a session, a
#: fleet root that is not one, and the calibration's typed errors (a parameter name, too
#: few poses). Named, not imported: ``loopcal --help`` imports none of them, and an
#: exception of a class whose module was never imported cannot have been raised.
BAD_INPUT: tuple[tuple[str, str], ...] = (
    ("loopcal.calibration.errors", "CalibrationError"),
    ("..config.controller", "ControllerConfigError"),
    ("..recorder.settings", "SettingsError"),
    ("..recorder.ownership", "ModuleHeld"),
    ("..recording.errors", "RecordingError"),
    ("..live.control", "ControlError"),
    ("..inspect.fleet", "FleetError"),
    ("loopcal.simulator.options", "SimulationError"),
)


def as_refusal(exc: BaseException) -> CommandError | None:
    """``exc`` as a command's refusal, or None if it is not one (a bug: let it through).

    Parameters
    ----------
    exc : BaseException
        What a command raised.

    Returns
    -------
    CommandError or None
        ``exc`` itself if it is a :class:`CommandError`; one with its message and status 2
        if it is one of :data:`BAD_INPUT`; else None.
    """
    if isinstance(exc, CommandError):
        return exc
    for module_name, class_name in BAD_INPUT:
        module = sys.modules.get(resolve_name(module_name, __package__))
        if module is not None and isinstance(exc, getattr(module, class_name)):
            return CommandError(exc)
    return None


def run_command(name: str, run: Callable[[argparse.Namespace], int],
                args: argparse.Namespace) -> int:  # fmt: skip
    """Run a command: its exit status, its refusal printed on stderr.

    Parameters
    ----------
    name : str
        The command, as typed (``init-config``).
    run : callable
        Its ``run(args) -> int``.
    args : argparse.Namespace
        Its parsed arguments.

    Returns
    -------
    int
        What ``run`` returned; for a refusal (:func:`as_refusal`), its status, after
        ``loopcal NAME: error: LINE`` on stderr for each line of its message. Anything
        else raised is raised on (a bug: a traceback).
    """
    try:
        return run(args)
    except Exception as exc:
        refusal = as_refusal(exc)
        if refusal is None:
            raise
    for line in str(refusal).splitlines() or [""]:
        print(f"loopcal {name}: error: {line}", file=sys.stderr)
    return refusal.status
