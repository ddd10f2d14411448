"""``loopcal calibrate``: new parameters from recordings, written only when they can be
trusted.

Reads one or several recordings (or a time window of the daemon's recording directory)
and identifies the free parameters, starting from the controller config: by maximum
likelihood from every usable scan, moving or still, each with a plate orientation of its
own (the default, ``--method ml``), or with ``--method paper`` from the still poses, of
which it selects the best ``--select``. Then it runs the acceptance gates. Without
``--write`` it changes nothing and shows the change it would make; with ``--write`` and
every gate passed, it writes the new values into the controller config (keeping the
previous version beside it). Exit status: 0 accepted (and written with ``--write``), 1 a
gate failed (nothing written), 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import TYPE_CHECKING

from loopcal.calibration.defaults import DEFAULT_FREE, DEFAULT_METHOD, DEFAULT_N_SELECT, METHODS

from ..arguments import (
    add_recordings_argument,
    duration_argument,
    path_argument,
    time_argument,
)
from ..times import time_or
from .errors import CommandError
from .model_options import add_model_options, add_select_option, parse_model
from .option_rules import note_given, refuse_unless

if TYPE_CHECKING:  # the worker, the recordings and the config: imported when run
    from ..worker.writeback import Written

#: the longest --last that makes sense: more than any recording kept on a controller
MAX_DURATION = timedelta(days=3650)


def last_argument(text: str) -> timedelta:
    """--last: a duration (:func:`~loopcal.daemon.arguments.duration_argument`) of at most
    :data:`MAX_DURATION`."""
    seconds = duration_argument(text)
    if seconds > MAX_DURATION.total_seconds():
        raise argparse.ArgumentTypeError(
            f"{text!r}: a duration must be more than 0 and at most {MAX_DURATION.days} days")
    return timedelta(seconds=seconds)


def add_arguments(p: argparse.ArgumentParser) -> None:
    note_given(p)
    add_recordings_argument(
        p, optional=True, help="recording files or directories of them (default with --config: "
        "its recordings directory)",
    )  # fmt: skip
    p.add_argument(
        "--controller-config",
        type=path_argument,
        metavar="PATH",
        help="the controller config to start from (and to write with --write)",
    )
    p.add_argument(
        "--config",
        type=path_argument,
        metavar="DAEMON.toml",
        help="take the recording directory and controller config from the daemon's "
        "config (what the systemd worker unit does)",
    )
    add_model_options(p, default=None,
                      default_text=f"the controller config's [calibration].free, else "
                                   f"{DEFAULT_FREE}")  # fmt: skip
    p.add_argument("--since", type=time_argument, metavar="TIME",
                   help="only scans from TIME on (as loopcal prints times, "
                        "2026-12-03T08:37:37.357Z, or any ISO 8601 time; UTC if it names no "
                        "zone)")  # fmt: skip
    p.add_argument("--until", type=time_argument, metavar="TIME",
                   help="only scans before TIME (as --since)")  # fmt: skip
    p.add_argument(
        "--last",
        type=last_argument,
        metavar="D",
        help="only the last DURATION of the recordings, by their stamps (90, 90s, 15m, 2h, 1d)",
    )
    add_select_option(p)
    p.add_argument(
        "--method",
        choices=METHODS,
        default=DEFAULT_METHOD,
        help="estimator: ml, maximum likelihood from every usable scan, moving or still "
        f"(default {DEFAULT_METHOD}), or paper, the paper's closed-loop residuals of the "
        "--select best still poses",
    )
    p.add_argument(
        "--write",
        action="store_true",
        help="write the new values into the controller config if every gate passes",
    )
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.add_argument("--report", type=path_argument, metavar="DIR",
                   help="write an HTML report with plots into DIR")  # fmt: skip


def _inputs(args: argparse.Namespace) -> tuple[list[Path], Path]:
    from ..recording import find_recordings
    from ..recording.names import recording_paths

    files: list[Path] = list(args.recordings)
    controller = args.controller_config
    if args.config is not None and files and controller is not None:
        raise CommandError("--config gives the recordings directory and the controller config; "
                           "both are given already: drop --config, or the recordings and "
                           "--controller-config")  # fmt: skip
    if args.config is not None:
        # the daemon's settings check driver URLs (pymodbus): loaded only for --config
        from ..recorder.settings import load_daemon_config

        settings = load_daemon_config(args.config)
        if not files:
            files = [settings.directory]
        if controller is None:
            controller = settings.controller_config
    if controller is None:
        raise CommandError(
            "no controller config: give --controller-config PATH (or --config with a "
            "[controller] config)"
        )
    if not files:
        raise CommandError("no recordings given: name REC.mcap files or a directory, or use "
                           "--config")
    out: list[Path] = []
    for f in files:
        if f.is_dir():
            found = find_recordings(f)
            if not found:
                raise CommandError(f"{f}: no recordings (loopcal-*.mcap) in this directory")
            out += found
        else:
            out += recording_paths([f])  # a regular file, or why not
    return out, controller


def check_report_dir(directory: Path) -> None:
    """The report's directory must be one (or creatable) and take files, before anything
    is computed or written."""
    if directory.exists() and not directory.is_dir():
        raise CommandError(f"--report {directory}: exists and is not a directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".loopcal-write-test.{os.getpid()}"
        probe.touch(exist_ok=False)
        probe.unlink()
    except OSError as exc:
        raise CommandError(f"--report {directory}: cannot write there: "
                           f"{exc.strerror or exc}") from None  # fmt: skip


def _window_text(since_ns: int | None, until_ns: int | None) -> str:
    lo, hi = time_or(since_ns, "the start"), time_or(until_ns, "the end")
    return f"from {lo} to {hi}"


@dataclass(frozen=True)
class Calibration:
    """What ``loopcal calibrate`` is asked, its inputs found: the command's body as
    :func:`calibrate` runs it (``loopcal session`` runs it on a session's window).

    files: the recordings. controller_path: the controller config to start from and to
    write. free, ties: the free set (None: the config's, else the default). since_ns,
    until_ns: the scans stamped from ``since_ns`` on and before ``until_ns``, ns since the
    Unix epoch (None: open). last: the last stretch instead of
    ``since``. select, method: as the options. write, json, report: as the options.
    extra: more keys for the JSON document. json_indent: its indent (None: one line).
    """

    files: list[Path]
    controller_path: Path
    free: str | None = None
    ties: str | None = None
    since_ns: int | None = None
    until_ns: int | None = None
    last: timedelta | None = None
    select: int = DEFAULT_N_SELECT
    method: str = DEFAULT_METHOD
    write: bool = False
    json: bool = False
    report: Path | None = None
    extra: dict = field(default_factory=dict)
    json_indent: int | None = 1


def run(args: argparse.Namespace) -> int:
    refuse_unless(args, args.method == "paper", "only with --method paper",
                  f"the default method ({DEFAULT_METHOD}) fits every usable scan and selects "
                  "no poses", "--select")  # fmt: skip
    if args.ties is not None and not args.free:
        raise CommandError("--ties goes with --free (ties tie parameters of a custom free set)")
    if args.free:  # a bad free set or ties is named before any file is read
        parse_model(args.free, args.ties)
    files, controller_path = _inputs(args)
    return calibrate(Calibration(
        files, controller_path, free=args.free, ties=args.ties, since_ns=args.since,
        until_ns=args.until, last=args.last, select=args.select, method=args.method,
        write=args.write, json=args.json, report=args.report))  # fmt: skip


def calibrate(job: Calibration) -> int:
    """Read, fit, check the gates, report, and write if asked and accepted: the exit
    status (0 accepted, 1 refused), everything said on stdout and stderr. Bad input
    raises :class:`~loopcal.daemon.commands.errors.CommandError` (or a domain error that
    means it: a controller config, a recording), before anything is written."""
    from loopcal.calibration.parameters import ParameterModel

    from ..config import durable
    from ..config.controller import load_controller_config
    from ..recording import read_recordings
    from ..worker.job import describe_files, run_worker
    from ..worker.writeback import check_writable, write_back

    def progress(text: str) -> None:
        print(text, file=sys.stderr if job.json else sys.stdout, flush=True)

    since, until = job.since_ns, job.until_ns
    if job.report is not None:
        check_report_dir(job.report)
    config = load_controller_config(job.controller_path)
    if job.write:
        check_writable(config)
    if job.free:
        model = parse_model(job.free, job.ties)
    else:
        model = ParameterModel.parse(config.free or DEFAULT_FREE, config.ties)
    if job.last is not None and since is not None:
        raise CommandError("give --since or --last, not both")
    if since is not None and until is not None and until <= since:
        raise CommandError(f"empty time window: --until is not after --since "
                           f"({_window_text(since, until)})")  # fmt: skip
    if job.select < model.n_free:
        raise CommandError(f"--select {job.select}: at least {model.n_free} poses are needed")
    progress(f"reading {len(job.files)} recording file(s)")
    rec = read_recordings(job.files, since=since, until=until, last=job.last)
    if job.last is not None and rec.since_ns is not None:  # where --last began
        since = rec.since_ns
    notes = describe_files(rec.files)
    if notes:
        progress(f"note: {notes}")
    for line in rec.warnings:
        progress(f"warning: {line}")
    if len(rec) == 0:
        window = since is not None or until is not None
        raise CommandError("no scans in the recordings"
                           + (f" {_window_text(since, until)}" if window else ""))
    result = run_worker(
        rec.scans, config, model, files=rec.files, n_select=job.select, method=job.method,
        progress=progress,
    )  # fmt: skip
    if job.report is not None:  # every other output first: the config is written last
        from ..worker.report import write_report  # matplotlib only when a report is asked for

        try:
            page = write_report(result, job.report, progress=progress)
        except OSError as exc:
            raise CommandError(f"cannot write the report in {job.report}: "
                               f"{exc.strerror or exc}; nothing written") from None  # fmt: skip
        progress(f"report: {page}")
    written = None
    if job.write and result.accepted:
        written = write_back(config, result.params, result.provenance(since=since, until=until))
    if job.json:
        doc = result.as_json()
        doc.update(
            {
                "written": written is not None,
                "config": str(config.path),
                "target": str(written.target if written else durable.target_of(config.path)),
                "previous_version": str(written.backup) if written else None,
                "warnings": rec.warnings,
                **job.extra,
            }
        )
        print(json.dumps(doc, indent=job.json_indent, default=_jsonable), flush=True)
    else:
        _print_human(result, config.path, written, job.write)
    return 0 if result.accepted else 1


def _jsonable(obj):
    if hasattr(obj, "item"):
        return obj.item()
    raise TypeError(f"not JSON serialisable: {obj!r}")


def _print_human(result, path, written: Written | None, asked_to_write: bool) -> None:
    from ..worker.job import METHOD_NAMES

    cal = result.calibration
    print()
    print(f"Free parameters: {result.model.describe()}")
    if cal is not None:
        ident = cal.identification
        if cal.selection is None:  # every usable scan, one rotation each
            blocks = len(set(result.poses.block[result.held_out].tolist()))
            used = (f"{int(ident.used.sum()):,} of {len(cal.indices):,} scans used, moving or "
                    f"still, one plate rotation each; {len(result.held_out):,} in {blocks} "
                    "stretches held out to check")  # fmt: skip
        else:
            used = (f"{int(ident.used.sum())} of {len(cal.indices)} selected poses used; "
                    f"{len(result.held_out)} held out to check")  # fmt: skip
        print(
            f"{used}; {METHOD_NAMES[ident.method]}: "
            + (
                f"rms misfit {1000 * ident.rms_residual:.1f} mV per scan"
                if ident.method == "ml"
                else f"rms residual {ident.rms_residual:.4g} mm^2"
            )
            + f", equivalent noise {1000 * ident.sigma_volts:.1f} mV "
            f"(the readings' scatter predicts {1000 * result.expected_noise_volts:.1f} mV)"
        )
        print()
        print(result.table())
    print()
    print("Acceptance gates:")
    for g in result.gates:
        print(g.line())
    print()
    if not result.accepted:
        names = ", ".join(g.name for g in result.failed)
        print(f"REFUSED ({names}): {path} is unchanged.")
    elif written is not None:
        where = str(written.target)
        if written.through_link:
            where += f" (through the symlink {written.path}, which stays a link)"
        print(
            f"Wrote {len(result.changed())} value(s) to {where}; the previous version is "
            f"{written.backup}."
        )
    elif asked_to_write:
        print(f"Nothing to write: {path} already holds these values.")
    else:
        print(f"Accepted. Nothing written: add --write to put these values in {path}.")
