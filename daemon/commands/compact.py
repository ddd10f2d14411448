"""``loopcal compact REC|DIR ...``: rewrite closed recordings with large chunks, for fast
reading (:mod:`loopcal.daemon.recording.compact`).

The daemon compacts every file it closes by itself (``[recording].compact``); this command
is for archives recorded before it did, or copied from elsewhere. Each file is verified scan
for scan against the original before it replaces it atomically; files not closed, damaged
or already compact are left as they are. Exit status 0, or 2 for bad input.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..recording import RecordingError
from ..recording.compact import compact, remove_stale_temporaries
from ..recording.names import recording_paths


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recordings", nargs="+", type=Path, metavar="REC.mcap|DIR",
                   help="recording files or directories of them")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    try:
        for p in args.recordings:
            if p.is_dir():
                remove_stale_temporaries(p)  # left by compactions that were killed
        files = recording_paths(args.recordings)
    except (RecordingError, OSError) as exc:
        print(f"loopcal compact: error: {exc}", file=sys.stderr)
        return 2
    before = after = 0
    for f in files:
        try:
            r = compact(f)
        except OSError as exc:
            print(f"{f}: not compacted: {exc.strerror or exc} (kept as it was)")
            continue
        if r.done:
            before, after = before + r.bytes_before, after + r.bytes_after
            print(f"{f}: {r.chunks_before} chunks -> {r.chunks_after}, "
                  f"{r.bytes_before:,} -> {r.bytes_after:,} bytes")  # fmt: skip
        else:
            print(f"{f}: left as it is ({r.reason})")
    if before:
        print(f"{before:,} -> {after:,} bytes")
    return 0
