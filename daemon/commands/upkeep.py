"""``loopcal upkeep status|apply|discard``: what the daemon's upkeep is doing, and the
recalibration it proposed.

``status`` shows, from the record the daemon keeps beside its recordings
(``upkeep-state.json``, :mod:`loopcal.daemon.live.upkeep_state`), whether the daemon runs or
not, and in every mode: since when it watches the config in force, whether its baseline is
ready, a change in progress (the offsets told apart, or the candidates, their shifts and
the move that would tell them apart), its last proposal or write, and its refusals; and
how well the config knows each offset (its std, the errors its fixes took in from the
offsets held counted), and whether that still vouches for the upkeep's threshold.

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
from ..times import time_json, time_text
from .errors import CommandError

if TYPE_CHECKING:  # the worker's proposals (numpy, tomlkit): imported by run
    from ..config.controller import ControllerConfig
    from ..worker.proposal import Proposal

ACTIONS = ("status", "apply", "discard")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("action", choices=ACTIONS,
                   help="status: show the proposal; apply: check and write it; discard: "
                        "set it aside")  # fmt: skip
    p.add_argument("--config", type=path_argument, metavar="DAEMON.toml",
                   help="the daemon's config: its controller config, recordings and "
                        "[upkeep].target_mm (e.g. /etc/loopcal/daemon.toml)")  # fmt: skip
    p.add_argument(
        "--controller-config",
        type=path_argument,
        metavar="PATH",
        help="the controller config the proposal is beside (without --config)",
    )
    p.add_argument(
        "--recordings",
        type=path_argument,
        metavar="DIR",
        help="the recordings apply checks the proposal on (without --config)",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def _where(args: argparse.Namespace) -> tuple[Path, Path | None, float, float, str | None]:
    """(controller config, recordings directory, target_mm, threshold_mm, the upkeep's
    mode as the daemon's config sets it or None) from the options."""
    from ..recorder.settings import DEFAULTS, load_daemon_config

    if args.config is not None:
        if args.controller_config is not None or args.recordings is not None:
            raise CommandError("give --config, or --controller-config and --recordings, not both")
        s = load_daemon_config(args.config)
        if s.controller_config is None:
            raise CommandError(f"{args.config}: no [controller].config: the daemon proposes "
                               "nothing without one")  # fmt: skip
        mode = s.upkeep_mode if s.upkeep_mode is not None else "propose"
        return s.controller_config, s.directory, s.upkeep_target_mm, s.upkeep_threshold_mm, mode
    if args.controller_config is None:
        raise CommandError("give --config DAEMON.toml, or --controller-config PATH")
    target, threshold = DEFAULTS["upkeep_target_mm"], DEFAULTS["upkeep_threshold_mm"]
    return args.controller_config, args.recordings, target, threshold, None


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


def _record(recordings: Path | None, config: ControllerConfig) -> tuple[dict | None, list[str]]:
    """The upkeep's kept record beside ``recordings``, for ``--json`` and in lines (None
    and a line saying why when there is none to show)."""
    from ..live.changes import BASELINE_SEGMENTS
    from ..live.upkeep_state import load_record, reference_digest, state_path

    if recordings is None:
        return None, ["the upkeep's record: give --config DAEMON.toml or --recordings DIR"]
    path = state_path(recordings)
    try:
        rec = load_record(path)
    except (ValueError, OSError) as exc:
        return None, [
            f"the upkeep's record {path} cannot be read ({exc}): the daemon sets it "
            "aside and starts over when it next starts"
        ]
    if rec is None:
        return None, [
            f"no upkeep record in {recordings}: the daemon has not watched with upkeep on there yet"
        ]
    ch, base = rec.change, rec.baseline.segments
    doc = {
        "record": str(path),
        "current": rec.reference == reference_digest(config.params),
        "watching_since_utc": time_json(rec.watching_since_ns or None),
        "tested_until_utc": time_json(rec.tested_until_ns or None),
        "baseline_segments": base,
        "baseline_ready": base >= BASELINE_SEGMENTS,
        "uncalibrated": rec.uncalibrated,
        "change": None
        if ch is None or not ch.stood
        else {
            "since_utc": time_json(ch.since_ns),
            "names": ch.names,
            "candidates": ch.candidates,
            "advice": ch.advice,
        },
        "last_action": rec.last_action,
        "refusals": rec.refusals,
        "last_refusal": rec.last_refusal,
    }
    lines = [f"the upkeep's record {path}, as of {_iso(rec.tested_until_ns or None)}:"]
    if not doc["current"]:
        lines.append(
            "  made at other values than this config's (a proposal pending, or a "
            "calibration since): the daemon goes on from the values in force"
        )
    lines.append(
        f"  watching since {_iso(rec.watching_since_ns or None)}; baseline "
        + ("ready" if doc["baseline_ready"] else "building")
        + f" ({base} of "
        f"{BASELINE_SEGMENTS} segments; the config's own calibration stands in "
        "meanwhile)" * (not doc["baseline_ready"])
    )
    if rec.uncalibrated:
        lines.append(
            "  the loops did not close at this config, which loopcal never "
            "calibrated: calibrate with loopcal session"
        )
    if doc["change"] is not None:
        words = " or ".join(
            " and ".join(
                f"{n} {s:+.3f} mm (+-{d:.3f})"
                for n, s, d in zip(c["names"], c["shift_mm"], c["std_mm"], strict=True)
            )
            for c in ch.candidates
        )
        lines.append(f"  LOOPS OPEN since {_iso(ch.since_ns)}: {words}")
        lines.append(
            "  told apart: identifying it from the robot's motion"
            if ch.names
            else f"  not told apart yet: to tell them apart, {ch.advice}"
        )
    elif not rec.uncalibrated:
        lines.append("  nothing changed since the baseline")
    if (act := rec.last_action) is not None:
        values = act.get("values") if isinstance(act.get("values"), dict) else {}
        lines.append(
            f"  last {act.get('kind', '?')} {_iso(act.get('ns'))}: "
            + ", ".join(f"{n} = {v} mm" for n, v in values.items())
            + (f" ({act['path']})" if act.get("path") else "")
        )
    if rec.refusals:
        last = rec.last_refusal or {}
        lines.append(
            f"  refused {rec.refusals} time{'s' * (rec.refusals > 1)}; the latest "
            f"{_iso(last.get('ns'))}: {last.get('why', '?')}"
        )
    return doc, lines


def _known(config: ControllerConfig, threshold_mm: float) -> tuple[dict | None, list[str]]:
    """How well the config knows its offsets (its fixes' carried errors counted), for
    ``--json`` and in lines: None and nothing for a config loopcal never calibrated."""
    from ..worker.offsets import UNSURE_SIGMAS, calibrated, offset_std, unsure_offsets

    if not calibrated(config):
        return None, []
    std = {n: round(s, 5) for n, s in offset_std(config).items()}
    unsure = dict(unsure_offsets(config, threshold_mm))
    line = "  offsets known to " + ", ".join(f"{n} +-{s:.3f} mm" for n, s in std.items())
    if unsure:
        line += (
            f"; OFFSETS UNCERTAIN ({', '.join(unsure)}): {UNSURE_SIGMAS:g} std reach the "
            f"{threshold_mm:g} mm threshold: calibrate with loopcal session"
        )
    return {"std_mm": std, "uncertain": sorted(unsure), "threshold_mm": threshold_mm}, [line]


def run(args: argparse.Namespace) -> int:
    from ..config.controller import ControllerConfigError, load_controller_config
    from ..worker.proposal import apply_proposal, discard_proposal, read_proposal

    config_path, recordings, target_mm, threshold_mm, mode = _where(args)
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
    elif args.action == "status":
        record, text = _record(recordings, config)
        known = _known(config, threshold_mm)
        out.update(mode=mode, record=record, offsets=known[0])
        text += known[1]
        if mode is not None:
            text.insert(0, f"upkeep: mode {mode}, beside {config_path}")
        if proposal is None:
            text.append(f"no recalibration proposed beside {config_path}")
            status = 1
        else:
            out.update(pending=True, path=str(proposal.path), values=proposal.values,
                       std=proposal.std, upkeep=proposal.upkeep)  # fmt: skip
            text, status = text + describe(proposal, config_path, recordings), 0
    elif proposal is None:
        text, status = [f"no recalibration proposed beside {config_path}"], 1
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
