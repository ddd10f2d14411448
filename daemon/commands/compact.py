"""``loopcal compact REC|DIR ... [--json]``: rewrite closed recordings with large chunks, for
fast reading (:mod:`loopcal.daemon.recording.compact`).

The daemon compacts every file it closes by itself (``[recording].compact``); this command
is for archives recorded before it did, or copied from elsewhere. Each file is verified scan
for scan against the original before it replaces it atomically; files not closed, damaged
or already compact are left as they are. Exit status 0 when every file is compact or left
for a good reason, 1 when a file could not be compacted (unreadable, its copy failed
verification, an I/O error; each kept as it was), 2 for bad input.

``--json``: one object, ``{"files": [{"path", "compacted", "failed", "reason",
"chunks_before", "chunks_after", "bytes_before", "bytes_after"}], "bytes_before",
"bytes_after", "failed"}``.
"""

from __future__ import annotations

import argparse
import json
import sys

from ..arguments import path_argument
from ..recording import RecordingError
from ..recording.compact import Compacted, compact, remove_stale_temporaries
from ..recording.names import recording_paths


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("recordings", nargs="+", type=path_argument, metavar="REC.mcap|DIR",
                   help="recording files or directories of them")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help="one JSON object on stdout: what was done to each file")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    try:
        for p in args.recordings:
            if p.is_dir():
                remove_stale_temporaries(p)  # left by compactions that were killed
        files = recording_paths(args.recordings)
    except (RecordingError, OSError) as exc:
        print(f"loopcal compact: error: {exc}", file=sys.stderr)
        return 2
    results: list[Compacted] = []
    for f in files:
        try:
            r = compact(f)
        except OSError as exc:
            r = Compacted(f, False, f"{exc.strerror or exc} (kept as it was)", failed=True)
        results.append(r)
        if args.json:
            continue
        if r.done:
            print(f"{f}: {r.chunks_before} chunks -> {r.chunks_after}, "
                  f"{r.bytes_before:,} -> {r.bytes_after:,} bytes")  # fmt: skip
        elif r.failed:
            print(f"{f}: not compacted: {r.reason}")
        else:
            print(f"{f}: left as it is ({r.reason})")
    done = [r for r in results if r.done]
    before, after = sum(r.bytes_before for r in done), sum(r.bytes_after for r in done)
    failed = sum(r.failed for r in results)
    if args.json:
        print(json.dumps({
            "files": [{"path": str(r.path), "compacted": r.done, "failed": r.failed,
                       "reason": r.reason, "chunks_before": r.chunks_before,
                       "chunks_after": r.chunks_after, "bytes_before": r.bytes_before,
                       "bytes_after": r.bytes_after} for r in results],
            "bytes_before": before, "bytes_after": after, "failed": failed,
        }, indent=1))  # fmt: skip
    elif before:
        print(f"{before:,} -> {after:,} bytes")
    if failed and not args.json:
        print(f"loopcal compact: {failed} file(s) could not be compacted (kept as they were)",
              file=sys.stderr)  # fmt: skip
    return 1 if failed else 0
