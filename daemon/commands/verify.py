"""``loopcal verify REC|DIR ... [--json]``: check every record of every file, as ``mcap doctor``
does, in the recording's own terms.

Every chunk (the views' chunks too: the reader skips those), its CRC, its decompression and
every record inside it; the message indexes after it; the metadata; the summary (chunk
indexes against the chunks they point to, statistics against the messages found, metadata
indexes, summary offsets) and the footer. Each damaged item is named with its byte offset,
what was wrong, the topics of its messages and their time span (UTC). The file is mapped,
not read into memory, and one chunk at a time is decompressed. ``--json`` prints one object
(docs/tools.md lists its keys). Exit status: 0 every record of every file checked out, 1
damage was found, 2 bad input.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..arguments import add_recordings_argument
from .errors import CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_recordings_argument(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from ..recording.names import recording_paths
    from ..recording.verify import verify_file

    try:
        files = recording_paths(args.recordings)
        if not files:
            raise CommandError(f"{', '.join(map(str, args.recordings))}: no recordings "
                               "(loopcal-*.mcap)")  # fmt: skip
        checked = [verify_file(f) for f in files]
    except OSError as exc:
        raise CommandError(exc) from None
    damaged = sum(len(v.damaged) for v in checked)
    if args.json:
        print(json.dumps({"files": [v.as_json() for v in checked], "damaged": damaged,
                          "ok": damaged == 0}, indent=1))  # fmt: skip
        return 1 if damaged else 0
    for v in checked:
        state = "closed" if v.closed else "not closed"
        messages = sum(v.messages.values())
        summary = (f"{v.records:,} records, {v.chunks:,} chunks, {messages:,} messages, "
                   f"{state}")  # fmt: skip
        if v.ok:
            print(f"{Path(v.path).name}: ok ({summary})")
            continue
        print(f"{Path(v.path).name}: {len(v.damaged)} damaged item(s) ({summary})")
        for d in v.damaged:
            print(f"  {d.text()}")
    bad = sum(1 for v in checked if not v.ok)
    print(f"{len(checked)} file(s): " + ("every record checked out" if not bad else
          f"{damaged} damaged item(s) in {bad} file(s)"))  # fmt: skip
    return 1 if damaged else 0
