"""``loopcal export REC|DIR ... --out DIR [--controller-config PATH] [--json]``: a recording
for Foxglove, with every view, made again from the raw scans of each file.

``loopcal compact --drop-views`` (or the daemon's ``[recording].keep_views_days``) leaves out
the per-scan views of old files (/joint/state, /plate/transform): every raw scan and event
stays. This command writes each given file anew into the directory ``--out`` (created if
missing), under the same name, as the recorder writes a file: the raw scans bit for bit, the
events, and the views (/joint/state of every scan, /plate/transform of every scan with a
pose, /plate/scene), computed at the parameters of the controller config the file records
in its ``controller_config`` metadata record, or at those of ``--controller-config PATH``
(a controller config TOML) when given. A file with its views works as well: its views are
made again, at the parameters chosen. The metadata records are the original's: the
``loopcal`` record says the format as written and the version of the loopcal that wrote the
file (the recorder's, if another, as ``recorded_version``) and gains ``exported_from`` (the
source file) and ``exported_utc``; the ``controller_config`` record is the one the views
were computed with. The file is written to ``.NAME.export.tmp`` in ``--out`` and renamed to
its name only when complete and fsynced: a killed export leaves no half file under the real
name (its temporary file is removed by the next export of that file).

Never overwrites: an output file that already exists is refused before anything is
written. A damaged file is exported with what it holds, its reader's warning printed. A
file whose controller config record cannot give the 20 parameters (a missing or
incomplete record) is not exported unless ``--controller-config`` is given; the others
still are.

``--json``: one object, ``{"files": [{"path", "out", "scans", "views", "warning",
"error"}], "failed"}``; ``out`` is null for a file not exported, ``views`` the number of
messages of each view topic written.

Exit status 0 when every file was exported whole, 1 when a file could not be exported or
was damaged (exported with what it holds), 2 for bad input, with a line ``loopcal export:
error: ...`` naming it: an empty path, a path that does not exist, one that is not a regular
file (a FIFO, a device), a directory holding no recordings, a file that is not a recording,
an ``--out`` that is not a directory, an output file that exists, a controller config that
cannot be read.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from ..arguments import add_recordings_argument, path_argument
from .errors import CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_recordings_argument(p)
    p.add_argument("--out", type=path_argument, required=True, metavar="DIR",
                   help="the directory to write the exported files to, each under its "
                        "original's name (created if missing; no file in it is "
                        "replaced)")  # fmt: skip
    p.add_argument("--controller-config", type=path_argument, metavar="PATH",
                   help="compute the views at this controller config's parameters instead "
                        "of those each file records")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help="one JSON object on stdout: what was done with each file")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from ..config.controller import load_controller_config
    from ..recording.compact import recordings_named
    from .exporter import Exported, export_file

    try:
        files = recordings_named(args.recordings)
        out: Path = args.out
        if os.path.lexists(out) and not out.is_dir():
            raise CommandError(f"--out {out}: exists and is not a directory")
        config = None
        if args.controller_config is not None:
            config = load_controller_config(args.controller_config)
        targets: dict[Path, Path] = {}
        for f in files:
            target = out / f.name
            if target in targets:
                raise CommandError(f"{f} and {targets[target]}: both would be exported to "
                                   f"{target}")  # fmt: skip
            if os.path.lexists(target):
                raise CommandError(f"{target}: exists")
            targets[target] = f
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CommandError(exc) from None
    results: list[Exported] = []
    for target, f in targets.items():
        try:
            r = export_file(f, target, config)
        except FileExistsError:
            r = Exported(f, error=f"{target}: exists (created meanwhile; left as it is)")
        except OSError as exc:
            r = Exported(f, error=f"{f}: not exported: {exc.strerror or exc}")
        results.append(r)
        if args.json:
            continue
        if r.out is not None:
            views = ", ".join(f"{t} {n:,}" for t, n in r.views.items())
            print(f"{f} -> {r.out}: {r.scans:,} scans; views: {views}")
        if r.warning:
            print(f"loopcal export: warning: {r.warning}", file=sys.stderr)
        if r.error and not r.not_recording:
            print(r.error, file=sys.stderr)
    failed = sum(r.failed for r in results)
    if args.json:
        print(json.dumps({"files": [r.as_json() for r in results], "failed": failed}, indent=1))
    strangers = [r for r in results if r.not_recording]
    not_whole = failed - len(strangers)
    if not_whole and not args.json:
        print(f"loopcal export: {not_whole} file(s) not exported or damaged", file=sys.stderr)
    if strangers:  # bad input found in a directory: each named, the others exported
        raise CommandError("\n".join(r.error for r in strangers))
    return 1 if failed else 0
