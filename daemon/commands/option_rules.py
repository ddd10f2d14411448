"""Options that mean something only with another: which options the command line gave, and
the refusal of those given where the command would ignore them.

An option left out keeps the parser's default (the one its ``--help`` prints), so the value
alone cannot tell ``--select 50`` from no ``--select``. :func:`note_given` makes a command's
parser remember which valued options the command line named; :func:`refuse_unless` raises
:class:`~loopcal.daemon.commands.errors.CommandError` (exit status 2) naming those given
that would change nothing, and why.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from .errors import CommandError

#: the attribute of the parsed arguments that holds the options given (:func:`given`)
GIVEN = "given_options"


class StoreGiven(argparse.Action):
    """argparse's ``store``, noting the option in the namespace's :data:`GIVEN` set (by its
    longest name, e.g. ``--select``).

    Parameters
    ----------
    option_strings, dest, nargs, **kwargs
        As for :class:`argparse.Action`; ``nargs`` 0 is refused, as ``store`` refuses it.
    """

    def __init__(self, option_strings: Sequence[str], dest: str, nargs: Any = None,
                 **kwargs: Any) -> None:  # fmt: skip
        if nargs == 0:
            raise ValueError("nargs for store actions must be != 0")
        super().__init__(option_strings, dest, nargs=nargs, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:  # fmt: skip
        setattr(namespace, self.dest, values)
        if self.option_strings:
            name = max(self.option_strings, key=len)
            setattr(namespace, GIVEN, frozenset(getattr(namespace, GIVEN, frozenset())) | {name})


def note_given(parser: argparse.ArgumentParser) -> None:
    """Make ``parser`` note every valued option the command line gives (those added after
    this call, with argparse's default action ``store``); :func:`given` reads them.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        A command's parser, before its options are added.
    """
    parser.register("action", None, StoreGiven)
    parser.register("action", "store", StoreGiven)
    parser.set_defaults(**{GIVEN: frozenset()})


def given(args: argparse.Namespace, *options: str) -> list[str]:
    """Which of ``options`` the command line gave, in the order asked.

    Parameters
    ----------
    args : argparse.Namespace
        Arguments parsed by a parser :func:`note_given` prepared.
    *options : str
        Option names, e.g. ``"--select"``.

    Returns
    -------
    list of str
        Those given.
    """
    named = getattr(args, GIVEN, frozenset())
    return [o for o in options if o in named]


def refuse_unless(args: argparse.Namespace, condition: bool, requirement: str, why: str,
                  *options: str) -> None:  # fmt: skip
    """Refuse the options of ``options`` given, unless ``condition`` holds.

    Parameters
    ----------
    args : argparse.Namespace
        Arguments parsed by a parser :func:`note_given` prepared.
    condition : bool
        Whether the options do something in this run.
    requirement : str
        When they apply, e.g. ``"only with --method paper"`` or ``"not with --session"``.
    why : str
        Why they do nothing otherwise, e.g. ``"the default method fits every scan and
        selects none"``.
    *options : str
        The options, e.g. ``"--select"``.

    Raises
    ------
    CommandError
        ``--select only with --method paper: the default method fits every scan and selects
        none``, naming every option of ``options`` given, if ``condition`` is false.
    """
    named = given(args, *options)
    if named and not condition:
        raise CommandError(f"{', '.join(named)} {requirement}: {why}")
