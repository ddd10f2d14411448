"""Read-back speed of the recording format: a day of 20 Hz scans into numpy arrays.

Writes (once, cached under ``--dir``) a day of recording as the daemon writes it: 1,728,000
scans at 20 Hz, one flush per second (a raw chunk and a views chunk each), rotated hourly
into 24 files, realistic codes. Then, each the median of ``--repeats`` runs:

* ``read day``: :func:`loopcal.daemon.recording.read_recordings` of the 24 files as the daemon
  keeps them: each compacted after its rotation (:mod:`loopcal.daemon.recording.compact`; target
  < 0.5 s); ``read day without views``: the same day as the daemon keeps it once its files
  are older than ``[recording].keep_views_days`` (compacted with ``drop_views``: target
  <= 12 B/scan on disk in all, raw scans <= 6); ``read day as written``: the same files
  before compaction (one chunk a second, what an unclosed file and recordings of older
  versions hold);
* ``read hour window``: one hour out of the day, by time window over all 24 files;
* ``read crashed hour``: one file cut short (no summary), read record by record;
* baseline, measured in the same run: the mcap library's message iterator
  (``make_reader(f).iter_messages()``) over every message of one file, in messages per
  second, and what a day would take at that rate if each scan were one message (the
  layout this format avoids). The ratio compares the two.

Run: ``python -m bench.bench_recording [--repeats 5] [--dir bench/results/day]``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import zstandard
from mcap.reader import make_reader

from bench._timing import median_time
from loopcal.daemon import recording as rec
from loopcal.daemon.recording.cdr import encode_scan_block
from loopcal.daemon.recording.compact import compact
from tests.support.recordings import compacted_copy, write_rows
from tests.support.sessions import hand_rows

RATE = 20
HOUR = 3600 * RATE


def write_day(directory: Path, hours: int) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    existing = rec.find_recordings(directory)
    if len(existing) == hours:
        return existing
    for p in existing:
        p.unlink()
    files = []
    t_start = time.perf_counter()
    for h in range(hours):
        # a technician moving the plate by hand, an hour's motion of its own
        rows = hand_rows(HOUR, seed=h + 1, first=h * HOUR)
        path = directory / rec.recording_name(int(rows["stamp_ns"][0]))
        meta = rec.metadata_records(device={"model": "LDQ412"}, controller={}, command="bench")
        write_rows(path, rows, per=RATE, metadata=meta, fsync=False)
        files.append(path)
        print(f"  wrote {path.name} ({path.stat().st_size / 1e6:.1f} MB), "
              f"{time.perf_counter() - t_start:.0f} s so far", flush=True)  # fmt: skip
    return files


def bytes_by_kind(files: list[Path]) -> dict[str, int]:
    """Bytes on disk of the chunks holding raw scans (with the events), of the views'
    chunks, and of everything else (header, metadata, indexes, summary)."""
    out = {"raw": 0, "views": 0, "rest": 0}
    for path in files:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        scans = {i for i, c in summary.channels.items() if c.topic == rec.TOPIC_SCANS}
        for ci in summary.chunk_indexes:
            raw = bool(scans & set(ci.message_index_offsets))
            out["raw" if raw else "views"] += ci.chunk_length
        out["rest"] += path.stat().st_size - sum(c.chunk_length for c in summary.chunk_indexes)
    return out


def rows_layout_bytes(scans: np.ndarray) -> int:
    """The raw scans as the former compaction kept them (ScanBlock rows, a minute to a
    zstd chunk at the mcap writer's level), measured here as the baseline."""
    zc = zstandard.ZstdCompressor()
    step = 60 * RATE
    return sum(len(zc.compress(encode_scan_block(scans[a : a + step])))
               for a in range(0, len(scans), step))  # fmt: skip


def iterate_all(path: Path) -> int:
    n = 0
    with open(path, "rb") as f:
        for _ in make_reader(f).iter_messages(log_time_order=False):
            n += 1
    return n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--hours", type=int, default=24)
    ap.add_argument("--dir", type=Path, default=Path(__file__).parent / "results" / "day")
    args = ap.parse_args()
    print(f"writing {args.hours} h of 20 Hz recording into {args.dir} (cached) ...")
    files = write_day(args.dir, args.hours)
    size = sum(p.stat().st_size for p in files)
    n_scans = args.hours * HOUR
    print(f"{len(files)} files, {size / 1e6:.0f} MB, {n_scans:,} scans "
          f"({size / n_scans:.0f} bytes per scan)")  # fmt: skip
    t_written, _ = median_time(lambda: rec.read_recordings(files), args.repeats)
    kept, t = compacted_copy(args.dir, args.dir.parent / "day-compacted")
    t_compact = t / len(files)
    compacted = rec.find_recordings(kept)
    size_c = sum(p.stat().st_size for p in compacted)
    print(f"compacted as the daemon does after each rotation: {t_compact:.1f} s a file, "
          f"{size_c / 1e6:.0f} MB")  # fmt: skip

    thin_dir = args.dir.parent / "day-thin"  # the compacted day, older than keep_views_days
    shutil.rmtree(thin_dir, ignore_errors=True)
    shutil.copytree(kept, thin_dir)
    thin = rec.find_recordings(thin_dir)
    t = time.perf_counter()
    for f in thin:
        if not compact(f, drop_views=True).done:
            raise SystemExit(f"could not leave out the views of {f}")
    t_thin_each = (time.perf_counter() - t) / len(thin)
    size_t = sum(p.stat().st_size for p in thin)

    t_day, out = median_time(lambda: rec.read_recordings(compacted), args.repeats)
    t_thin, out_t = median_time(lambda: rec.read_recordings(thin), args.repeats)
    assert out_t.scans.tobytes() == out.scans.tobytes()
    assert len(out) == n_scans and np.all(np.diff(out.scans["counter64"].astype(np.int64)) == 1)
    h0 = int(out.scans["stamp_ns"][HOUR * (args.hours // 2)])
    t_win, win = median_time(
        lambda: rec.read_recordings(files, since=h0, until=h0 + 3600 * 10**9), args.repeats
    )
    assert len(win) == HOUR
    crashed = args.dir.parent / "crashed.mcap"
    data = files[0].read_bytes()
    crashed.write_bytes(data[: int(len(data) * 0.9)])
    t_crash, cr = median_time(lambda: rec.read_recordings(crashed), args.repeats)
    crashed.unlink()
    t_iter, n_msgs = median_time(lambda: iterate_all(files[0]), max(1, args.repeats // 2))
    per_s = n_msgs / t_iter

    kinds = bytes_by_kind(compacted)
    baseline = rows_layout_bytes(out.scans)
    print(f"on disk, compacted: {size_c / n_scans:.1f} B/scan in all; raw scans (and events) "
          f"{kinds['raw'] / n_scans:.2f} B/scan (packed in columns; as rows, the former "
          f"layout, {baseline / n_scans:.2f} B/scan: {baseline / kinds['raw']:.1f}x); views "
          f"{kinds['views'] / n_scans:.1f} B/scan; the rest {kinds['rest'] / n_scans:.2f} "
          "B/scan")  # fmt: skip
    kinds_t = bytes_by_kind(thin)
    per_scan_t = size_t / n_scans
    print(f"on disk, compacted without views ({t_thin_each:.1f} s a file): {per_scan_t:.2f} "
          f"B/scan in all (target <= 12: {'met' if per_scan_t <= 12 else 'NOT met'}); raw "
          f"scans (and events) {kinds_t['raw'] / n_scans:.2f} B/scan (target <= 6: "
          f"{'met' if kinds_t['raw'] / n_scans <= 6 else 'NOT met'}); the scene and the rest "
          f"{(kinds_t['views'] + kinds_t['rest']) / n_scans:.2f} B/scan")  # fmt: skip
    day_mb, thin_mb = size_c / 1e6 * 24 / args.hours, size_t / 1e6 * 24 / args.hours
    year = 7 * day_mb + 358 * thin_mb
    print(f"a year on the robot at keep_views_days = 7: 7 days of {day_mb:.0f} MB and 358 of "
          f"{thin_mb:.1f} MB: {year / 1e3:.1f} GB (all with views: "
          f"{365 * day_mb / 1e3:.0f} GB)")  # fmt: skip
    print()
    print(f"read day           {t_day:6.2f} s   {n_scans / t_day:10,.0f} scans/s  "
          f"(target 1.7 M scans in < 0.5 s: {'met' if t_day < 0.5 else 'NOT met'})")  # fmt: skip
    print(f"read day w/o views {t_thin:6.2f} s   {n_scans / t_thin:10,.0f} scans/s  "
          f"(target < 0.5 s: {'met' if t_thin < 0.5 else 'NOT met'})")  # fmt: skip
    print(f"read day as written {t_written:5.2f} s   {n_scans / t_written:10,.0f} scans/s  "
          f"(uncompacted; compaction makes it {t_written / t_day:.1f}x faster)")  # fmt: skip
    print(f"read hour window   {t_win:6.2f} s   {len(win) / t_win:10,.0f} scans/s")
    print(f"read crashed hour  {t_crash:6.2f} s   {len(cr) / t_crash:10,.0f} scans/s  "
          f"({len(cr):,} scans up to the cut)")  # fmt: skip
    print(f"baseline: mcap iter_messages over every message of one file: {per_s:,.0f} msgs/s")
    naive = n_scans / per_s
    print(f"  a day as one message per scan at that rate: {naive:.1f} s; "
          f"this format reads it {naive / t_day:.1f}x faster")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
