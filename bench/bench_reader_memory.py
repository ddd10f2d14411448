"""Peak memory of reading one recording file: a closed file is mapped, not copied.

Writes (or takes) an hour of 20 Hz recording, closed and cut short (a crash: no summary),
and reads each in a fresh subprocess, printing the file's size, the Python heap's peak
during the read (``tracemalloc``) and the process's peak resident size (``ru_maxrss``,
which counts the mapped file's pages that were read, reclaimable page cache).

Run: ``python -m bench.bench_reader_memory [--minutes 60] [FILE ...]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from loopcal.daemon import recording as rec
from tests.support.recordings import write_rows
from tests.support.rows import T0, rows_from

_CHILD = """
import resource, sys, tracemalloc
from loopcal.daemon import recording as rec
tracemalloc.start()
out = rec.read_recordings(sys.argv[1])
peak = tracemalloc.get_traced_memory()[1]
rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(len(out), peak, rss)
"""


def write_hour(path: Path, minutes: int) -> None:
    """``minutes`` of 20 Hz scans, one flush a second, as the daemon writes them."""
    n = minutes * 60 * 20
    c = np.arange(n, dtype=np.int64)
    rows = rows_from(c * 50_000, 2048 + (c[:, None] % 40) + np.zeros((1, 4), dtype=np.int64))
    meta = rec.metadata_records(device={"model": "LDQ412"}, controller={}, command="bench")
    write_rows(path, rows, metadata=meta, fsync=False)


def measure(path: Path) -> tuple[int, int, int]:
    """(scans, tracemalloc peak bytes, ru_maxrss KiB) of reading ``path`` in a subprocess."""
    out = subprocess.run([sys.executable, "-c", _CHILD, str(path)], check=True,
                         capture_output=True, text=True).stdout.split()  # fmt: skip
    scans, peak, rss = (int(x) for x in out)
    return scans, peak, rss


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=int, default=60)
    ap.add_argument("files", nargs="*", type=Path)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        files = list(args.files)
        if not files:
            closed = Path(tmp) / rec.recording_name(T0)
            write_hour(closed, args.minutes)
            crashed = Path(tmp) / "crashed.mcap"
            data = closed.read_bytes()
            crashed.write_bytes(data[: int(len(data) * 0.9)])
            files = [closed, crashed]
        for path in files:
            scans, peak, rss = measure(path)
            size = path.stat().st_size
            print(f"{path.name:40s} {size / 1e6:6.1f} MB  {scans:8,} scans  "
                  f"heap peak {peak / 1e6:6.1f} MB ({peak / size:4.2f}x the file)  "
                  f"ru_maxrss {rss / 1e3:6.0f} MB")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
