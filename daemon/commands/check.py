"""``loopcal check REC|DIR ... --controller-config PATH [--json] [--plot FILE]``: did the loops
close at this config, and if not, which sensor moved, when, and by how much.

The daemon's loop-closure health (:mod:`loopcal.daemon.live.health`: the same code, the same
false-alarm rate) run offline over archived recordings, file by file in time order (memory
stays that of one file). For every change it finds: the sensor, when the change began (the
first still pose it shifted; UTC and seconds into the recordings), when it was detected,
the shift in mm with its standard deviation, whether it was a step or is still creeping,
and when the loops closed again, if they did. Loops that do not close from the first poses
on are not a change: the config does not describe the robot (a sensor replaced before the
recordings, a config never calibrated), and that is said instead, once ("loops_open" in
``--json``). Still poses are counted as ``loopcal info`` counts them, the one the
recordings end in included. ``--plot FILE`` draws each sensor's estimated offset shift over
time and the test statistic against the alarm threshold, into FILE as its name says (.png,
.svg or .pdf), titled by the verdict the text ends with.

The same scans go to the daemon's upkeep in report mode (:mod:`loopcal.daemon.inspect.proposals`,
``--upkeep-target-mm`` and ``--upkeep-threshold-mm``, the daemon's defaults): for each
recalibration it would have proposed from the robot's own motion, the offsets, the values
it would write with their std, the shifts, when the change began and the window of scans
fitted ("proposals" in ``--json``). A proposal pending beside the config (the daemon's
``.proposed`` file) is named, or why it cannot be read ("pending_proposal").

Exit status: 0 the loops close and nothing would be proposed, 1 a change was found, the
loops never closed or a recalibration would be proposed, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from ..arguments import add_recordings_argument, path_argument
from ..defaults import FALSE_ALARM, FALSE_ALARM_MAX, UPKEEP_TARGET_MM, UPKEEP_THRESHOLD_MM
from .errors import CommandError

if TYPE_CHECKING:  # the health monitor and the upkeep (numpy, scipy): imported when run
    from ..inspect.proposals import UpkeepSettings

#: the image formats --plot writes, by the file name's suffix
PLOT_FORMATS = (".png", ".svg", ".pdf")


def plot_argument(text: str) -> Path:
    """--plot: a file name ending in one of :data:`PLOT_FORMATS` (the format it is written
    in: a name without one is refused, not given one)."""
    path = path_argument(text)
    if path.suffix.lower() not in PLOT_FORMATS:
        raise argparse.ArgumentTypeError(
            f"{text!r}: name the image file with its format, one of "
            f"{', '.join(PLOT_FORMATS)} (e.g. check.png)")  # fmt: skip
    return path


def check_plot_file(path: Path) -> None:
    """The plot's directory must exist and take files, before anything is computed."""
    directory = path.parent
    if not directory.is_dir():
        raise CommandError(f"--plot {path}: directory {directory} does not exist")
    if path.is_dir():
        raise CommandError(f"--plot {path}: is a directory")
    if not os.access(directory, os.W_OK | os.X_OK) or (path.exists()
                                                        and not os.access(path, os.W_OK)):
        raise CommandError(f"--plot {path}: cannot write there (permission denied)")


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_recordings_argument(p)
    p.add_argument("--controller-config", type=path_argument, required=True, metavar="PATH",
                   help="the controller config to check the loops against")  # fmt: skip
    add_false_alarm_option(p)
    add_upkeep_options(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--plot", type=plot_argument, metavar="FILE.png",
                   help="draw each sensor's estimated shift and statistic over time into this "
                        f"file ({', '.join(PLOT_FORMATS)})")  # fmt: skip


def add_false_alarm_option(p: argparse.ArgumentParser, *, what: str = "") -> None:
    """``--false-alarm P``, the daemon's rate by default (``loopcal check``, ``loopcal fleet
    check``, whose help says ``what`` first); :func:`check_false_alarm` checks it."""
    p.add_argument("--false-alarm", type=float, default=FALSE_ALARM, metavar="P",
                   help=f"{what}probability per still pose of an alarm when nothing moved "
                        f"(default {FALSE_ALARM:g}, the daemon's)")  # fmt: skip


def check_false_alarm(p: float) -> None:
    """Raises CommandError, naming the option, for a ``--false-alarm`` outside (0, 0.01)."""
    if not 0 < p < FALSE_ALARM_MAX:
        raise CommandError(f"--false-alarm {p:g}: give a probability in (0, {FALSE_ALARM_MAX:g})")


def add_upkeep_options(p: argparse.ArgumentParser, *, what: str = "") -> None:
    """``--upkeep-target-mm MM`` and ``--upkeep-threshold-mm MM``, the daemon's ``[upkeep]``
    defaults (``loopcal check``, ``loopcal fleet check``, whose help says ``what`` first);
    :func:`upkeep_settings` reads and checks them."""
    p.add_argument("--upkeep-target-mm", type=float, default=UPKEEP_TARGET_MM, metavar="MM",
                   help=f"{what}the standard deviation an offset the upkeep would propose must "
                        f"reach, mm (default {UPKEEP_TARGET_MM:g}, the daemon's "
                        "[upkeep].target_mm)")  # fmt: skip
    p.add_argument("--upkeep-threshold-mm", type=float, default=UPKEEP_THRESHOLD_MM,
                   metavar="MM",
                   help=f"{what}the smallest change of an offset the upkeep acts on, mm "
                        f"(default {UPKEEP_THRESHOLD_MM:g}, the daemon's "
                        "[upkeep].threshold_mm)")  # fmt: skip


def upkeep_settings(args: argparse.Namespace) -> UpkeepSettings:
    """The upkeep's settings :func:`add_upkeep_options` parsed; raises CommandError naming
    the option for a value outside the daemon's bounds."""
    from ..inspect.proposals import UpkeepSettings

    try:
        return UpkeepSettings(target_mm=args.upkeep_target_mm,
                              threshold_mm=args.upkeep_threshold_mm).checked()  # fmt: skip
    except ValueError as exc:  # the options' values, named by checked()
        raise CommandError(exc) from None


def run(args: argparse.Namespace) -> int:
    check_false_alarm(args.false_alarm)
    upkeep = upkeep_settings(args)
    if args.plot is not None:
        check_plot_file(args.plot)
    from ..inspect.loops import check, plot, sensor_words, verdict
    from ..recording.names import recording_paths

    try:
        files = recording_paths(args.recordings)
        if not files:
            raise CommandError("no recordings (loopcal-*.mcap) in " +
                               ", ".join(map(str, args.recordings)))  # fmt: skip
        doc = check(files, args.controller_config, args.false_alarm,
                    trace=args.plot is not None, upkeep=upkeep)  # fmt: skip
    except OSError as exc:  # a file named or found that cannot be read
        raise CommandError(exc) from None
    if args.plot is not None:
        try:
            plot(doc, args.plot)
        except OSError as exc:
            raise CommandError(f"--plot {args.plot}: cannot write it: "
                               f"{exc.strerror or exc}") from None  # fmt: skip
    doc.pop("_trace")
    found = verdict(doc)
    if args.json:
        print(json.dumps(doc, indent=1))
    else:
        for line in doc["warnings"]:
            print(f"warning: {line}")
        print(f"{doc['poses']:,} still poses from {doc['start_utc']} to {doc['end_utc']}, "
              f"against {doc['config']['path']}")  # fmt: skip
        if doc["loops_close"]:
            print("The loops close: no sensor's offset moved.")
        if (o := doc["loops_open"]) is not None and o["calibrated_utc"]:
            print(f"The loops do not close at this config since the recordings began (all "
                  f"{o['poses']} poses from {o['since_utc']} on disagree with it): something "
                  f"changed since its calibration ({o['calibrated_utc']}), before the "
                  f"recordings; the largest difference: sensor {o['largest_sensor']}'s "
                  f"offset, {o['largest_shift_mm']:+.3f} mm.")  # fmt: skip
        elif o is not None:
            print(f"The loops do not close at this config since the recordings began (all "
                  f"{o['poses']} poses from {o['since_utc']} on disagree with it; nothing "
                  f"moved during the recordings): the config does not describe this robot, "
                  f"calibrate (loopcal session). Largest apparent difference: sensor "
                  f"{o['largest_sensor']}'s offset, {o['largest_shift_mm']:+.3f} mm, though "
                  "a config never calibrated is off in every parameter.")  # fmt: skip
        for c in doc["changes"]:
            shape = "a creep, still moving" if c["shape"] == "creep" else "a step"
            end = (f"; the loops closed again at {c['end_utc']}" if c["end_utc"] else
                   "; the loops have not closed again")  # fmt: skip
            who = (f"sensor {c['sensor']}" if c["sensor"] is not None else
                   f"sensor {sensor_words(c)} (the poses could not tell which)")  # fmt: skip
            print(f"{who}: offset moved by {c['shift_mm']:+.3f} mm "
                  f"(+- {c['std_mm']:.3f}, {shape}), from {c['start_utc']} "
                  f"({c['start_offset_s']:,.0f} s into the recordings), detected "
                  f"{c['detected_utc']}{end}")  # fmt: skip
        print_proposals(doc)
        print(f"Verdict: {found.text}.")
        if args.plot is not None:
            print(f"plot: {args.plot}")
    return found.status


def print_proposals(doc: dict) -> None:
    """The text of what the upkeep would propose, and of a proposal pending beside the
    config."""
    from ..inspect.proposals import proposal_words

    for p in doc["proposals"]:
        into = ("" if p["since_offset_s"] is None
                else f" ({p['since_offset_s']:,.0f} s into the recordings)")  # fmt: skip
        print(f"upkeep would propose {proposal_words(p)}: changed since {p['since_utc']}"
              f"{into}; fitted on {p['scans']:,} scans from {p['window_since_utc']} to "
              f"{p['window_until_utc']}, every gate passed")  # fmt: skip
    if not doc["proposals"]:
        print("upkeep would propose no recalibration.")
    if (pending := doc["pending_proposal"]) is not None:
        if pending["error"] is not None:
            where = "" if pending["path"] in pending["error"] else f" {pending['path']}"
            print(f"pending proposal{where}: cannot be taken: {pending['error']}")
        else:
            values = ", ".join(f"{n} = {v:.4f} mm" for n, v in pending["values"].items())
            print(f"pending proposal {pending['path']} since {pending['since_utc']}: {values}")
