"""``loopcal info REC|DIR ...``: what recordings hold, in the robot's own terms.

What ``mcap info`` and ``ros2 bag info`` give, for the shoulder joint: the files, the time
span (UTC), the scans and the scan rate, missed scans and gaps, when the module was powered
on and its restarts since, events by kind, the still poses a calibration would find, the
controller config in force (path, sha256, when and how it was calibrated) and anything
damaged: every record of every file is checked, the views' chunks, the indexes and the
statistics included (as ``loopcal verify`` does), and each damaged item is named with its byte
offset, the topics of its messages and their time span. ``damaged: none`` only when every
record checked out. ``--json`` prints one object (docs/tools.md lists its keys). Exit status
0 (damage is reported, not judged: ``loopcal verify`` exits 1 on it), 2 for bad input.

Files are read one at a time (memory stays that of one file, whatever the span); a scan in
two files (a copy, or a recorder that restarted) is counted once.
"""

from __future__ import annotations

import argparse
import json

from ..arguments import add_recordings_argument
from .errors import CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_recordings_argument(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--no-poses", action="store_true",
                   help="do not look for still poses (faster)")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from ..inspect.summary import collect, render

    try:
        s = collect(args.recordings, poses=not args.no_poses)
    except OSError as exc:
        raise CommandError(exc) from None
    doc = s.as_json()
    if args.json:
        print(json.dumps(doc, indent=1))
        return 0
    print("\n".join(render(doc)))
    return 0
