"""``loopcal upkeep status|apply|discard``: the recalibration the daemon proposed.

The daemon's upkeep (``[upkeep].mode = "propose"``, the default with a controller config)
writes a complete controller config beside the one in force when it finds, from the
robot's own motion, that an offset changed: ``controller.toml.proposed``. ``status`` shows
it (what changed, since when, the values, their std, the gates, the window of scans, and
the command that draws it as plots); ``apply`` checks its gates again on its own window of
the recordings and writes it through the normal path (the previous version kept beside,
provenance recorded; the daemon follows the new file); ``discard`` renames it aside
(``.discarded``), and the daemon does not propose the same change again.

A proposal that was damaged or edited by hand, or made from another version of the
config, is refused, naming why, and nothing is written. Exit status: 0 done (status: a
proposal pending), 1 none pending (status), or the gates refuse it now (apply), 2 bad
input.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from ..arguments import path_argument
from ..times import time_text
from .errors import CommandError

if TYPE_CHECKING:  # the worker's proposals (numpy, tomlkit): imported by run
    from ..worker.proposal import Proposal

ACTIONS = ("status", "apply", "discard")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=ACTIONS,
                   help="status: show the proposal; apply: check and write it; discard: "
                        "set it aside")  # fmt: skip
    p.add_argument("--config", type=path_argument, metavar="DAEMON.toml",
                   help="the daemon's config: its controller config, recordings and "
                        "[upkeep].target_mm (e.g. /etc/loopcal/daemon.toml)")  # fmt: skip
    p.add_argument("--controller-config", type=path_argument, metavar="PATH",
                   help="the controller config the proposal is beside (without --config)")
    p.add_argument("--recordings", type=path_argument, metavar="DIR",
                   help="the recordings apply checks the proposal on (without --config)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def _where(args: argparse.Namespace) -> tuple[Path, Path | None, float]:
    """(controller config, recordings directory, target_mm) from the options."""
    from ..recorder.settings import DEFAULTS, load_daemon_config

    if args.config is not None:
        if args.controller_config is not None or args.recordings is not None:
            raise CommandError("give --config, or --controller-config and --recordings, not both")
        s = load_daemon_config(args.config)
        if s.controller_config is None:
            raise CommandError(f"{args.config}: no [controller].config: the daemon proposes "
                               "nothing without one")  # fmt: skip
        return s.controller_config, s.directory, s.upkeep_target_mm
    if args.controller_config is None:
        raise CommandError("give --config DAEMON.toml, or --controller-config PATH")
    return args.controller_config, args.recordings, DEFAULTS["upkeep_target_mm"]


def _iso(ns: object) -> str:
    return time_text(ns) if isinstance(ns, int) else "?"


def describe(p: Proposal, config_path: Path, recordings: Path | None) -> list[str]:
    """The proposal in lines for people."""
    up = p.upkeep
    lines = [f"a recalibration is proposed in {p.path}", f"  {p.describe()}"]
    for name, v in p.values.items():
        lines.append(f"  {name}: {v:.4f} mm (was {v - up.get('shift_mm', {}).get(name, 0):.4f}"
                     f", shift {up.get('shift_mm', {}).get(name, 0):+.4f} +- "
                     f"{p.std.get(name, float('nan')):.4f} mm)")  # fmt: skip
    gates = up.get("gates", {})
    lines.append("  gates: " + " ".join(f"{g}{'+' if ok else '-'}" for g, ok in gates.items()))
    lines.append(f"  fitted on {up.get('scans', '?')} scans from {_iso(up.get('window_since_ns'))}"
                 f" to {_iso(up.get('window_until_ns'))}")  # fmt: skip
    where = "RECORDINGS" if recordings is None else str(recordings)
    lines.append(
        "  review it as plots: loopcal calibrate --controller-config "
        f"{config_path} --free {','.join(p.values)} --since {_iso(up.get('window_since_ns'))} "
        f"--until {_iso(up.get('window_until_ns'))} --report DIR {where}")  # fmt: skip
    lines.append("  then: loopcal upkeep apply (or discard)")
    return lines


def run(args: argparse.Namespace) -> int:
    from ..config.controller import ControllerConfigError, load_controller_config
    from ..worker.proposal import apply_proposal, discard_proposal, read_proposal

    config_path, recordings, target_mm = _where(args)
    config = load_controller_config(config_path)
    try:
        proposal = read_proposal(config)
    except ControllerConfigError as exc:
        if args.action != "discard":
            raise
        print(f"loopcal upkeep: the proposal cannot be read ({exc}); discarding it",
              file=sys.stderr)  # fmt: skip
        proposal = None
    out: dict = {"action": args.action, "config": str(config_path), "pending": False}
    if args.action == "discard":
        aside = discard_proposal(config)
        out.update(discarded=aside is not None, aside=None if aside is None else str(aside))
        text = [f"set aside as {aside}" if aside else "no proposal to discard"]
        status = 0
    elif proposal is None:
        text, status = [f"no recalibration proposed beside {config_path}"], 1
    elif args.action == "status":
        out.update(pending=True, path=str(proposal.path), values=proposal.values,
                   std=proposal.std, upkeep=proposal.upkeep)  # fmt: skip
        text, status = describe(proposal, config_path, recordings), 0
    else:
        if recordings is None:
            raise CommandError("apply needs the recordings to check the proposal on: "
                               "--config DAEMON.toml, or --recordings DIR")  # fmt: skip
        try:
            written = apply_proposal(config, proposal, recordings, target_mm=target_mm)
        except ControllerConfigError as exc:
            if "gates refuse" not in str(exc) and "3 std" not in str(exc):
                raise
            out.update(applied=False, problem=str(exc))
            text, status = [f"not applied: {exc}"], 1
        else:
            out.update(applied=True, path=str(written.path), previous=str(written.backup),
                       values=proposal.values)  # fmt: skip
            text = [f"applied: {', '.join(f'{n} = {v:.4f} mm' for n, v in proposal.values.items())}"
                    f" written into {written.path} (the previous version kept as "
                    f"{written.backup})"]  # fmt: skip
            status = 0
    if args.json:
        print(json.dumps(out, default=str))
    else:
        print("\n".join(text))
    return status
