"""``loopcal compact REC|DIR ... [--drop-views] [--json]``: rewrite closed recordings in chunks
of a minute, for fast reading (:mod:`loopcal.daemon.recording.compact`).

The daemon compacts every file it closes by itself (``[recording].compact``); this command
is for archives recorded before it did, or copied from elsewhere. Each file is verified scan
for scan against the original before it replaces it atomically; files not closed, damaged
or already compact are left as they are. Exit status 0 when every file is compact or left
for a good reason, 1 when a file could not be compacted (damaged, its copy failed
verification, an I/O error; each kept as it was), 2 for bad input, with a line
``loopcal compact: error: ...`` naming it: an empty path, a path that does not exist, one
that is not a regular file (a FIFO, a device), a directory holding no recordings, a file
that is not a recording (not MCAP, an MCAP file of something else, another format). Bad
input named on the command line is refused before any file is touched; a file found in a
directory that turns out not to be a recording is reported so, and the exit status is 2.

``--drop-views``: leave out the per-scan views (/joint/state, /plate/transform), nine tenths of
a compacted file: what stays is every raw scan, bit for bit, the events and the metadata
(about 5 bytes a scan against 120). ``loopcal export`` makes a file with every view again.
The daemon does this by itself to files older than ``[recording].keep_views_days``.

``--json``: one object, ``{"files": [{"path", "compacted", "failed", "not_recording", "reason",
"chunks_before", "chunks_after", "bytes_before", "bytes_after"}], "bytes_before",
"bytes_after", "failed"}``.
"""

from __future__ import annotations

import argparse
import json
import sys

from ..arguments import add_recordings_argument
from .errors import CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_recordings_argument(p)
    p.add_argument("--drop-views", action="store_true",
                   help="leave out the per-scan views (/joint/state, /plate/transform): every "
                        "raw scan and event stays; loopcal export makes them again")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help="one JSON object on stdout: what was done to each file")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from ..recording.compact import (
        Compacted,
        compact,
        recordings_named,
        remove_stale_temporaries,
    )

    try:
        files = recordings_named(args.recordings)
        for p in args.recordings:
            if p.is_dir():
                remove_stale_temporaries(p)  # left by compactions that were killed
    except OSError as exc:
        raise CommandError(exc) from None
    results: list[Compacted] = []
    for f in files:
        try:
            r = compact(f, drop_views=args.drop_views)
        except OSError as exc:
            r = Compacted(f, False, f"{exc.strerror or exc} (kept as it was)", failed=True)
        results.append(r)
        if args.json:
            continue
        if r.done:
            print(f"{f}: {r.chunks_before} chunks -> {r.chunks_after}, "
                  f"{r.bytes_before:,} -> {r.bytes_after:,} bytes")  # fmt: skip
        elif r.not_recording:
            print(f"{f}: not compacted: not a recording")
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
                       "not_recording": r.not_recording,
                       "reason": r.reason, "chunks_before": r.chunks_before,
                       "chunks_after": r.chunks_after, "bytes_before": r.bytes_before,
                       "bytes_after": r.bytes_after} for r in results],
            "bytes_before": before, "bytes_after": after, "failed": failed,
        }, indent=1))  # fmt: skip
    elif before:
        print(f"{before:,} -> {after:,} bytes")
    strangers = [r for r in results if r.not_recording]
    if failed > len(strangers) and not args.json:
        print(f"loopcal compact: {failed - len(strangers)} file(s) could not be compacted "
              "(kept as they were)", file=sys.stderr)  # fmt: skip
    if strangers:  # bad input found in a directory: each named, the others done
        raise CommandError("\n".join(r.reason for r in strangers))
    return 1 if failed else 0
