"""``loopcal record``: record the DAQ to MCAP files in the foreground, for a technician or a
test. The same engine as ``loopcal daemon``; stops after ``--duration`` or on SIGINT/SIGTERM
with the file properly closed; SIGHUP re-reads the controller config and starts a new file.

With ``--until-enough`` it guides the technician live (:mod:`loopcal.daemon.live.guidance`): a
display redrawn about once a second (plain lines when stdout is not a terminal, one JSON object per
update with ``--json``), and it stops by itself once every offset's predicted standard
deviation is at or below ``--target-mm`` and the calibration's acceptance gates would pass.
Exit status then: 0 enough, 1 stopped before it was enough.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from loopcal.calibration.errors import ParameterError

from ..config.controller import ControllerConfigError
from ..events import Level
from ..live.guidance import OFFSETS, Guidance, GuidanceUpdate
from ..live.health import watch_health
from ..recorder.engine import Recorder
from ..recorder.process import run_recorder, setup_logging
from ..recorder.settings import RecorderSettings, SettingsError, parse_size


def _size(text: str) -> int:
    try:
        return parse_size(int(text) if text.isdigit() else text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    d = RecorderSettings("x://", Path())
    p.add_argument(
        "--daq",
        required=True,
        metavar="URL",
        help="driver URL, e.g. modbus-tcp://192.168.1.50:502?unit=1",
    )
    p.add_argument(
        "--out",
        required=True,
        type=Path,
        metavar="DIR",
        help="directory for the recordings (created if missing)",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="stop after this many seconds (default: until SIGINT/SIGTERM)",
    )
    p.add_argument(
        "--controller-config",
        type=Path,
        default=None,
        metavar="PATH",
        help="controller config for the recorded poses (default: reference geometry)",
    )
    p.add_argument(
        "--timeout",
        type=float,
        default=d.timeout_s,
        metavar="S",
        help=f"answer timeout (default {d.timeout_s:g})",
    )
    p.add_argument(
        "--read-period",
        type=float,
        default=d.read_period_s,
        metavar="S",
        help=f"seconds between FIFO reads (default {d.read_period_s:g})",
    )
    p.add_argument(
        "--flush-period",
        type=float,
        default=d.flush_period_s,
        metavar="S",
        help=f"seconds between flushes to disk, at most 1 (default {d.flush_period_s:g})",
    )
    p.add_argument(
        "--rotate-seconds",
        type=float,
        default=d.rotate_seconds,
        metavar="S",
        help=f"new file after this long (default {d.rotate_seconds:g})",
    )
    p.add_argument(
        "--rotate-size",
        type=_size,
        default=d.rotate_bytes,
        metavar="SIZE",
        help="new file once this big, e.g. 256MiB (default 256 MiB)",
    )
    p.add_argument(
        "--disk-budget",
        type=_size,
        default=0,
        metavar="SIZE",
        help="delete the oldest recordings in DIR to stay under this (default: keep all)",
    )
    p.add_argument(
        "--max-backlog-scans",
        type=int,
        default=d.max_backlog_scans,
        metavar="N",
        help=f"scans kept in memory while the disk fails (default {d.max_backlog_scans})",
    )
    p.add_argument(
        "--until-enough",
        action="store_true",
        help="guide the technician live and stop once the recording calibrates well enough",
    )
    p.add_argument(
        "--target-mm",
        type=float,
        default=0.1,
        metavar="MM",
        help="with --until-enough: every offset's standard deviation to reach (default 0.1)",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="with --until-enough: one JSON object per update on stdout instead of a display",
    )
    p.add_argument(
        "--metrics",
        default=None,
        metavar="HOST:PORT",
        help="serve Prometheus metrics on http://HOST:PORT/metrics, e.g. 127.0.0.1:9464",
    )
    p.add_argument(
        "--no-compact",
        action="store_true",
        help="keep closed files as written (one-second chunks), not compacted for reading",
    )
    p.add_argument(
        "--no-health",
        action="store_true",
        help="do not watch loop closure (no offset_drift events)",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")  # fmt: skip


def settings_from_args(args: argparse.Namespace) -> RecorderSettings:
    return RecorderSettings(
        daq_url=args.daq,
        directory=args.out,
        timeout_s=args.timeout,
        read_period_s=args.read_period,
        flush_period_s=args.flush_period,
        rotate_seconds=args.rotate_seconds,
        rotate_bytes=args.rotate_size,
        disk_budget_bytes=args.disk_budget,
        max_backlog_scans=args.max_backlog_scans,
        controller_config=args.controller_config,
        duration_s=args.duration,
        health=not args.no_health,
        metrics_listen=args.metrics,
        compact=not args.no_compact,
    ).checked()


def run(args: argparse.Namespace) -> int:
    setup_logging(args.verbose)
    guide: Guidance | None = None
    try:
        if (args.json or args.target_mm != 0.1) and not args.until_enough:
            raise SettingsError("--json and --target-mm go with --until-enough")
        settings = settings_from_args(args)
        recorder = Recorder(settings, command="loopcal record " + " ".join(sys.argv[2:]))
        watch_health(recorder)
        if args.until_enough:
            controller = recorder.controller
            guide = Guidance(
                controller, controller.model(), target_mm=args.target_mm,
                on_update=Display(json_lines=args.json).update,
                on_enough=lambda u: _enough(recorder, u),
            )  # fmt: skip
            recorder.add_observer(guide)
    except (SettingsError, ControllerConfigError, ParameterError, ValueError) as exc:
        print(f"loopcal record: error: {_flag_names(str(exc))}", file=sys.stderr)
        return 2
    status = run_recorder(recorder)
    st = recorder.status
    log = logging.getLogger(__name__)
    log.info(
        "stopped (%s): %d scans in %d file(s) in %s",
        recorder.exit_reason, st.scans_written, st.files_written, settings.directory,
    )  # fmt: skip
    if status == 0 and st.scans_written == 0:
        acq = recorder.acquisition_stats
        if acq is not None and acq.scans:
            why = (f"{acq.scans} scans arrived but none could be written to "
                   f"{settings.directory}: {st.disk_error or 'see the errors above'}")  # fmt: skip
        else:
            why = acq.last_error if acq is not None and acq.last_error else "no scan arrived"
        log.error("nothing was recorded: %s", why)
        return 1
    if guide is not None and status == 0 and not guide.done:
        log.warning("stopped before the recording was enough to calibrate")
        return 1
    return status


def _enough(recorder: Recorder, u: GuidanceUpdate) -> None:
    worst = max(u.std.get(n, 0.0) for n in OFFSETS)
    recorder.emit(
        "guidance", Level.INFO,
        f"enough: {u.poses} still poses, every offset within {worst:.3f} mm (target "
        f"{u.target_mm:g} mm), every acceptance gate passes",
        enough=True, poses=u.poses, std=u.std, target_mm=u.target_mm,
    )  # fmt: skip
    recorder.request_stop("enough to calibrate")


class Display:
    """The live guidance on stdout: redrawn in place on a terminal (plain ANSI, fine over
    SSH), a block per update otherwise, or one JSON object per line."""

    def __init__(self, *, json_lines: bool) -> None:
        self.json_lines = json_lines
        self.tty = sys.stdout.isatty()
        self._lines = 0

    def update(self, u: GuidanceUpdate) -> None:
        if self.json_lines:
            print(json.dumps(u.as_json()), flush=True)
            return
        lines = u.render()
        if self.tty:
            # back to the top of the previous display, clear it, draw again
            up = f"\x1b[{self._lines}F" if self._lines else ""
            sys.stdout.write(up + "\x1b[J" + "\n".join(lines) + "\n")
            sys.stdout.flush()
            self._lines = len(lines)
        else:
            print("\n".join(lines) + "\n", flush=True)


def _flag_names(message: str) -> str:
    """Settings errors name the daemon config's keys; say the command's options instead."""
    for key, flag in (("[daq].url", "--daq"), ("[daq].timeout", "--timeout"),
                      ("[daq].read_period", "--read-period"),
                      ("[recording].directory", "--out"),
                      ("[recording].flush_period", "--flush-period"),
                      ("[recording].rotate_seconds", "--rotate-seconds"),
                      ("[recording].rotate_size", "--rotate-size"),
                      ("[recording].disk_budget", "--disk-budget"),
                      ("[recording].max_backlog_scans", "--max-backlog-scans"),
                      ("[controller].config", "--controller-config"),
                      ("[metrics].listen", "--metrics")):  # fmt: skip
        message = message.replace(key, flag)
    return message
