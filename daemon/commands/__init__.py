"""The ``loopcal`` commands: one module per command, loaded only when it runs.

Each module has ``add_arguments(parser)``, ``run(args) -> int`` (the exit status) and a
docstring (or ``DESCRIPTION``) for its ``--help``. :data:`COMMANDS` lists them with their
one-line helps, so that
``loopcal --help`` imports none of them; :func:`load` imports one. ``loopcal.daemon.cli`` builds the
parser from these and dispatches.

Imports: everything below it in daemon/ (the recorder, the worker, live analysis, the
recording format, the config), and the simulator for the commands that serve an emulated
module. Never ``loopcal.daemon.cli``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

#: (name, one-line help) in the order ``loopcal --help`` lists them
COMMANDS: tuple[tuple[str, str], ...] = (
    ("demo",
     "the field job on an emulated DAQ: record a session, calibrate, write, check the truth"),
    ("record", "record the DAQ to MCAP files in the foreground"),
    ("probe", "is the DAQ there, and what is it; if not, why not (within 5 s)"),
    ("daemon", "the acquisition daemon (systemd's entry point): record the DAQ for months"),
    ("session",
     "calibrate through the running daemon: live guidance, then the session's scans calibrated"),
    ("upkeep",
     "the recalibration the daemon proposed from the robot's motion: status, apply, discard"),
    ("init-config",
     "write a controller config (TOML) with the 20 parameters at the reference geometry"),
    ("calibrate",
     "identify new parameters from recordings; --write puts them in the controller config"),
    ("info",
     "what recordings hold: time span, scans, gaps, restarts, events, poses, config, damage"),
    ("verify",
     "check every record of recordings (views, indexes, statistics): name each damaged part"),
    ("check", "did the loops close at a controller config: which sensor moved, when, by how much"),
    ("fleet", "info or check over a fleet's archives, per robot and day, on Dask (loopcal[fleet])"),
    ("compact", "rewrite closed recordings in chunks of a minute, for fast reading (verified)"),
    ("export",
     "a recording for Foxglove with every view, made again from the raw scans (views dropped)"),
    ("replay", "serve a recording through the emulated DAQ, scan for scan"),
    ("simulate", "serve an emulated LDQ-412 driven by a simulated shoulder joint"),
    ("observability", "which of the chosen free parameters the workspace can identify"),
    ("files", "the files loopcal ships: systemd units, Foxglove layouts, the docs; where they are"),
    ("install-units", "put the systemd units, sysusers and tmpfiles entries in place under a root"),
)  # fmt: skip


def load(name: str) -> ModuleType:
    """The module of command ``name`` (imported now): ``name`` with ``_`` for ``-``. Raises
    KeyError for an unknown one."""
    if name not in {n for n, _ in COMMANDS}:
        raise KeyError(name)
    return importlib.import_module(f".{name.replace('-', '_')}", __name__)
