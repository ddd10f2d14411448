"""What one damaged byte of a compacted recording costs: scans lost, by the byte hit.

    python -m bench.fuzz_compacted [--minutes 60] [--cases 40] [--seed 1] [--every-bit]

Writes ``--minutes`` of 20 Hz recording with the daemon's own writer (a flush a second, an
event every 10 s, as ``bench/bench_recording.py`` writes its day; a daemon's file is an
hour), closes it, and compacts it twice, in the same run:

* ``old``: the former layout (raw scans and events in chunks of 4 MiB, then the views in
  chunks of 4 MiB: an hour's scans in one chunk);
* ``new``: :func:`loopcal.daemon.recording.compact.compact` as it is (chunks of at most
  ``CHUNK_SPAN_NS`` of scans, each minute's views' chunk after its scans' one);
* ``thin``: the same without its views (``compact(..., drop_views=True)``, as the daemon
  keeps files older than ``[recording].keep_views_days``): the minutes' scan chunks side by
  side.

Every byte of each file is put in a class by the record it belongs to (magic, header,
metadata, scan chunk, views chunk, message index, data end, the summary's chunk indexes and
its other records, footer). For each class, ``--cases`` random bytes of it are damaged, one
mutant at a time: one bit flipped (``bit``), and 4,096 bytes zeroed from there (``zero4k``,
a torn page). Each mutant is read by :func:`loopcal.daemon.recording.read_recordings`, and
the scans it lost are counted against the original (a scan returned that the original does
not hold, scans lost without a warning, a RecordingError or any other exception is counted
as a failure, and as every scan lost). ``--every-bit`` also flips every bit of the new
layout's magic, header and metadata records in turn (the records a reader parses without a
CRC). The table
gives, per layout, mutation and class, the cases, the median and the largest loss (scans,
and seconds at 20 Hz), and the failures; the last lines say whether the new layout met the
target (one damaged byte anywhere costs at most 60 s of scans).
"""

from __future__ import annotations

import argparse
import collections
import io
import random
import statistics
import struct
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from loopcal.calibration.parameters import NOMINAL
from loopcal.calibration.simulate import simulate_poses
from loopcal.daemon import recording as rec
from loopcal.daemon.events import Event, Level
from loopcal.daemon.recording.compact import compact
from loopcal.drivers.ldq412 import volts_to_code
from tests.support.rows import T0, rows_from

RATE = 20
TARGET_S = 60
ZERO_RUN = 4096
MAGIC = b"\x89MCAP0\r\n"
_OLD_CHUNK_BYTES = 4 << 20  # the former compaction's chunks
_RAW_TOPICS = (rec.TOPIC_SCANS, rec.TOPIC_EVENTS, rec.TOPIC_LOG)
_OPCODES = {0x01: "header", 0x02: "footer", 0x03: "schema", 0x04: "channel", 0x05: "message",
            0x06: "chunk", 0x07: "message index", 0x08: "chunk index", 0x09: "attachment",
            0x0A: "attachment index", 0x0B: "statistics", 0x0C: "metadata",
            0x0D: "metadata index", 0x0E: "summary offset", 0x0F: "data end"}  # fmt: skip


def write_original(path: Path, minutes: int) -> int:
    """A closed recording of ``minutes`` at 20 Hz by the daemon's writer, a flush a second
    (the codes of a plate moved by hand, still for 2 s at a time), an event every 10 s.
    Returns the number of scans."""
    n = minutes * 60 * RATE
    codes = volts_to_code(simulate_poses(2000, seed=3).volts)
    c = np.arange(n, dtype=np.int64)
    rows = rows_from(c * 50_000, codes[(c // 40) % len(codes)])
    meta = rec.metadata_records(device={"model": "LDQ412"}, controller={}, command="fuzz")
    w = rec.RecordingWriter(path, metadata=meta, params=NOMINAL, fsync=False)
    for k in range(0, n, RATE):
        stamp = int(rows["stamp_ns"][k])
        events = []
        if k % (10 * RATE) == 0:
            events = [Event(stamp, "rail", Level.WARNING, f"channel 2 at the rail ({k})",
                            {"channel": 2, "on": True, "counter64": k})]  # fmt: skip
        w.write(rows[k : k + RATE], events)
    w.close()
    return n


def old_layout(src: Path, dst: Path) -> None:
    """``src`` rewritten as the former compaction did: the same records, the raw scans and
    events in chunks of 4 MiB, then the views in chunks of 4 MiB."""
    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f, validate_crcs=True)
        header, summary = reader.get_header(), reader.get_summary()
        assert summary is not None
        w = Writer(out, chunk_size=_OLD_CHUNK_BYTES, compression=CompressionType.ZSTD,
                   enable_crcs=True)  # fmt: skip
        w.start(profile=header.profile, library=header.library)
        sids = {sid: w.register_schema(s.name, s.encoding, s.data)
                for sid, s in sorted(summary.schemas.items())}  # fmt: skip
        for _, ch in sorted(summary.channels.items()):
            w.register_channel(ch.topic, ch.message_encoding, sids.get(ch.schema_id, 0),
                               dict(ch.metadata))  # fmt: skip
        stamp = datetime.now(UTC).isoformat(timespec="seconds")
        for m in reader.iter_metadata():
            record = dict(m.metadata)
            if m.name == "loopcal":
                record["compacted_utc"] = stamp
            w.add_metadata(m.name, record)
        views = {ch.topic for ch in summary.channels.values()} - set(_RAW_TOPICS)
        for topics in (_RAW_TOPICS, views):
            for _, ch, msg in reader.iter_messages(topics, log_time_order=False):
                w.add_message(ch.id, msg.log_time, msg.data, msg.publish_time, msg.sequence)
            w.flush()
        w.finish()


def byte_classes(data: bytes) -> dict[str, list[tuple[int, int]]]:
    """The (offset, length) ranges of each class of bytes of an intact, closed file: its
    records walked one by one (a chunk is one record), a chunk classed by what its index
    entry says it holds."""
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    scans = {cid for cid, c in summary.channels.items() if c.topic == rec.TOPIC_SCANS}
    raw = {cid for cid, c in summary.channels.items() if c.topic in _RAW_TOPICS}
    kind = {}
    for ci in summary.chunk_indexes:
        ids = set(ci.message_index_offsets)
        kind[ci.chunk_start_offset] = ("scan chunk" if ids & scans else
                                       "events chunk" if ids & raw else "views chunk")  # fmt: skip
    out: dict[str, list[tuple[int, int]]] = collections.defaultdict(list)
    out["magic"] += [(0, 8), (len(data) - 8, 8)]
    pos, in_summary = 8, False
    while pos < len(data) - 8:
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        name = _OPCODES.get(op, f"opcode {op:#x}")
        if op == 0x06:
            name = kind[pos]
        elif in_summary and op != 0x02:
            name = "summary: chunk index" if op == 0x08 else "summary: other"
        out[name].append((pos, 9 + length))
        in_summary = in_summary or op == 0x0F
        pos += 9 + length
    return dict(out)


def pick(ranges: list[tuple[int, int]], rng: random.Random) -> int:
    """A byte offset drawn uniformly from the bytes of ``ranges``."""
    total = sum(n for _, n in ranges)
    k = rng.randrange(total)
    for off, n in ranges:
        if k < n:
            return off + k
        k -= n
    raise AssertionError


def mutate(data: bytes, how: str, at: int, rng: random.Random) -> bytes:
    """``data`` with one bit of byte ``at`` flipped (``how="bit"``), or ZERO_RUN bytes
    zeroed from it (``"zero4k"``)."""
    out = bytearray(data)
    if how == "bit":
        out[at] ^= 1 << rng.randrange(8)
    else:
        out[at : at + ZERO_RUN] = bytes(len(out[at : at + ZERO_RUN]))
    return bytes(out)


def scans_lost(path: Path, original: set[int]) -> tuple[int | None, str]:
    """(scans of the original the mutant at ``path`` did not give back, "") or (None, what
    failed: a RecordingError, another exception, scans the original does not hold)."""
    try:
        out = rec.read_recordings(path)
    except rec.RecordingError as exc:
        return None, f"RecordingError: {exc}"[:120]
    except Exception as exc:  # noqa: BLE001 - what the fuzz is about
        return None, f"undeclared {type(exc).__name__}: {exc}"[:120]
    got = out.scans["counter64"].tolist()
    if not set(got) <= original or len(set(got)) != len(got):
        return None, "fabricated or duplicated scans"
    info = out.files[0]
    lost = len(original) - len(got)
    if lost and not info.warning:
        return None, f"{lost} scans lost without a warning"
    return lost, ""


def every_bit(data: bytes, mutant: Path, original: set[int],
              failures: dict[str, list[str]]) -> None:  # fmt: skip
    """Flip every bit of the magic, header and metadata records of ``data``, one at a time,
    and print how many flips lost scans or failed, and where; failures are added to
    ``failures["new"]``."""
    classes = byte_classes(data)
    flips, bad = 0, collections.Counter()
    for cls in ("magic", "header", "metadata"):
        for off, n in classes[cls]:
            for at in range(off, off + n):
                for bit in range(8):
                    out = bytearray(data)
                    out[at] ^= 1 << bit
                    mutant.write_bytes(bytes(out))
                    lost, why = scans_lost(mutant, original)
                    flips += 1
                    if lost is None:
                        failures["new"].append(f"bit {bit} of byte {at} ({cls}): {why}")
                    if lost != 0:
                        bad[(cls, at, data[at : at + 1])] += 1
    where = ", ".join(f"{n} at byte {at} ({cls}, {b!r})" for (cls, at, b), n in bad.items())
    print(f"every bit of the new layout's magic, header and metadata: {flips:,} flips, "
          f"{sum(bad.values())} lost scans or failed{': ' + where if where else ''}")  # fmt: skip


def main() -> int:
    """Run the fuzz; exit status 0 if the new layout met the target, else 1."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=int, default=60, help="length of the file (a daemon's: 60)")
    ap.add_argument("--cases", type=int, default=40, help="damaged bytes per class and mutation")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--every-bit", action="store_true",
                    help="also flip every bit of the new layout's magic, header and metadata, "
                         "one at a time")  # fmt: skip
    args = ap.parse_args()
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory(prefix="fuzz-compacted-", dir="/dev/shm"
                                     if Path("/dev/shm").is_dir() else None) as tmp:  # fmt: skip
        d = Path(tmp)
        name = rec.recording_name(T0)
        written = d / "written" / name
        written.parent.mkdir()
        t = time.perf_counter()
        n = write_original(written, args.minutes)
        print(f"{args.minutes} min at {RATE} Hz: {n:,} scans, {written.stat().st_size:,} bytes "
              f"as written ({time.perf_counter() - t:.0f} s)")  # fmt: skip
        original = set(rec.read_recordings(written).scans["counter64"].tolist())
        layouts = {}
        (d / "old").mkdir()
        old_layout(written, d / "old" / name)
        layouts["old"] = (d / "old" / name).read_bytes()
        (d / "new").mkdir()
        new = d / "new" / name
        new.write_bytes(written.read_bytes())
        r = compact(new)
        assert r.done, r
        layouts["new"] = new.read_bytes()
        (d / "thin").mkdir()
        thin = d / "thin" / name
        thin.write_bytes(written.read_bytes())
        r = compact(thin, drop_views=True)
        assert r.done, r
        layouts["thin"] = thin.read_bytes()
        mutant = d / "mutant" / name
        mutant.parent.mkdir()
        rows = []
        worst: dict[str, tuple[int, str, str]] = {}
        failures: dict[str, list[str]] = collections.defaultdict(list)
        for layout, data in layouts.items():
            classes = byte_classes(data)
            chunks = {k: len(v) for k, v in classes.items() if k.endswith("chunk")}
            mutant.write_bytes(data)
            assert scans_lost(mutant, original) == (0, ""), layout
            t = time.perf_counter()
            read = rec.read_recordings(mutant)
            t_read = time.perf_counter() - t
            print(f"{layout}: {len(data):,} bytes, chunks {chunks}, read in {t_read:.3f} s")
            for how in ("bit", "zero4k"):
                for cls, ranges in classes.items():
                    losses = []
                    for _ in range(args.cases):
                        at = pick(ranges, rng)
                        mutant.write_bytes(mutate(data, how, at, rng))
                        lost, why = scans_lost(mutant, original)
                        if lost is None:
                            failures[layout].append(f"{how} at byte {at} ({cls}): {why}")
                            lost = len(original)
                        losses.append(lost)
                        key = f"{layout} {how}"
                        if lost > worst.get(key, (-1, "", ""))[0]:
                            worst[key] = (lost, cls, f"byte {at}")
                    rows.append((layout, how, cls, len(losses), statistics.median(losses),
                                 max(losses)))  # fmt: skip
            del read
        print()
        print(f"{'layout':6} {'damage':7} {'bytes hit':22} {'cases':>5} "
              f"{'median lost':>17} {'max lost':>17}")  # fmt: skip
        for layout, how, cls, cases, med, mx in rows:
            print(f"{layout:6} {how:7} {cls:22} {cases:5} {med:9,.0f} ({med / RATE:5.1f} s) "
                  f"{mx:9,} ({mx / RATE:5.1f} s)")  # fmt: skip
        print()
        for key, (lost, cls, where) in worst.items():
            print(f"worst, {key}: {lost:,} of {n:,} scans ({lost / RATE:.1f} s), {cls}, {where}")
        for layout, fails in failures.items():
            print(f"{layout}: {len(fails)} failure(s)" + "".join(f"\n  {f}" for f in fails[:5]))
        if args.every_bit:
            every_bit(layouts["new"], mutant, original, failures)
        met = True
        for layout in ("new", "thin"):
            ok = worst[f"{layout} bit"][0] <= TARGET_S * RATE and not failures.get(layout)
            met &= ok
            print(f"target (one damaged byte anywhere: at most {TARGET_S} s of scans) "
                  f"{'met' if ok else 'NOT met'} by the {layout} layout")  # fmt: skip
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
