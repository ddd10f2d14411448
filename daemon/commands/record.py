"""``loopcal record``: record the DAQ to MCAP files in the foreground, for a technician or a
test. The same engine as ``loopcal daemon``; stops after ``--duration`` or on SIGINT/SIGTERM
with the file properly closed; SIGHUP re-reads the controller config and starts a new file.

With ``--until-enough`` it guides the technician live (:mod:`loopcal.daemon.live.guidance`): a
display redrawn about once a second (plain lines when stdout is not a terminal, one JSON object per
update with ``--json``), and it stops by itself once every offset's predicted standard
deviation is at or below ``--target-mm`` and the calibration's acceptance gates would pass.
Exit status then: 0 enough, 1 stopped before it was enough.

A duration D is seconds or a number with a unit: ``90``, ``90s``, ``15m``, ``2h``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from typing import TYPE_CHECKING

from ..events import Level
from ..recorder.settings import SettingsError, add_options, option_name, settings_from_args
from .errors import CommandError
from .guidance_display import add_guidance_options, target_mm

if TYPE_CHECKING:  # the recorder and live analysis (numpy, mcap, ...): imported by run
    from ..live.guidance import Guidance, GuidanceUpdate
    from ..recorder.engine import Recorder


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_options(p)  # every recorder setting that has an option (docs/daemon.md's table)
    add_guidance_options(
        p, until_enough="guide the technician live and stop once the recording calibrates "
        "well enough", target_with="with --until-enough: ",
    )  # fmt: skip
    p.add_argument(
        "--json",
        action="store_true",
        help="JSON lines on stdout: with --until-enough one object per guidance update, "
        'then always one summary object ("summary": true) when it stops',
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from ..live.guidance import Guidance
    from ..live.health import watch_health
    from ..live.upkeep import watch_upkeep
    from ..live.view import watch_live
    from ..recorder.engine import Recorder
    from ..recorder.process import run_recorder, setup_logging
    from .guidance_display import Display

    setup_logging(args.verbose)
    guide: Guidance | None = None
    if args.target_mm is not None and not args.until_enough:
        raise CommandError("--target-mm goes with --until-enough")
    try:
        settings = settings_from_args(args)
        recorder = Recorder(settings, command="loopcal record " + " ".join(sys.argv[2:]))
        monitor = watch_health(recorder)
        live = watch_live(recorder, settings.live_listen, health=monitor)
        upkeep = watch_upkeep(recorder)
        if args.until_enough:
            controller = recorder.controller
            display = Display(json_lines=args.json).update

            def update(u: GuidanceUpdate) -> None:
                display(u)
                if live is not None:
                    live.guidance(u)

            guide = Guidance(
                controller, controller.model(),
                target_mm=target_mm(args),
                on_update=update, on_enough=lambda u: _enough(recorder, u),
            )  # fmt: skip
            recorder.add_observer(guide)
    except SettingsError as exc:
        raise CommandError(exc.named(option_name)) from None
    try:
        status = run_recorder(recorder)
    finally:
        if upkeep is not None:
            upkeep.close()
        if live is not None:
            live.close()
    st = recorder.status
    log = logging.getLogger(__name__)
    log.info(
        "stopped (%s): %d scans in %d file(s) in %s",
        recorder.exit_reason, st.scans_written, st.files_written, settings.directory,
    )  # fmt: skip
    problem = None
    if status == 0 and st.scans_written == 0:
        acq = recorder.acquisition_stats
        if acq is not None and acq.scans:
            why = (f"{acq.scans} scans arrived but none could be written to "
                   f"{settings.directory}: {st.disk_error or 'see the errors above'}")  # fmt: skip
        else:
            why = acq.last_error if acq is not None and acq.last_error else "no scan arrived"
        problem = f"nothing was recorded: {why}"
        log.error("%s", problem)
        status = 1
    elif guide is not None and status == 0 and not guide.done:
        problem = "stopped before the recording was enough to calibrate"
        log.warning("%s", problem)
        status = 1
    if args.json:
        print(json.dumps({
            "summary": True, "exit_status": status, "stopped": recorder.exit_reason,
            "scans_written": int(st.scans_written), "files_written": int(st.files_written),
            "directory": str(settings.directory),
            "enough": guide.done if guide is not None else None, "problem": problem,
        }), flush=True)  # fmt: skip
    return status


def _enough(recorder: Recorder, u: GuidanceUpdate) -> None:
    from ..live.guidance import OFFSETS

    worst = max(u.std.get(n, 0.0) for n in OFFSETS)
    recorder.emit(
        "guidance", Level.INFO,
        f"enough: {u.poses} still poses, every offset within {worst:.3f} mm (target "
        f"{u.target_mm:g} mm), every acceptance gate passes",
        enough=True, poses=u.poses, std=u.std, target_mm=u.target_mm,
    )  # fmt: skip
    recorder.request_stop("enough to calibrate")
