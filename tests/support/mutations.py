"""Inputs damaged the way storage and wires damage them, and what the reader made of a
damaged recording judged.

Shared by the tests and the long fuzz run (bench/fuzz_parsers.py). A mutation is a plain
function of the file's bytes and a few integers, so hypothesis can draw the integers and
shrink them.
"""

from __future__ import annotations

import io
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.exceptions import EndOfFile
from mcap.records import Chunk, DataEnd
from mcap.stream_reader import StreamReader
from numpy.lib.recfunctions import repack_fields

from loopcal.daemon import recording as rec

from .recordings import write_recording

#: answers of the LDQ-412's ASCII protocol as the module sends them (the fuzzers mutate them)
ASCII_ANSWERS = [b">0000123400ABCDEF800001FFFBB80004\r", b"!01LDQ412\r", b"!012.01\r",
                 b"!010014\r", b">800\r", b"?01\r"]  # fmt: skip

#: a daemon config as an installation has it, every key set (the TOML fuzzers mutate it)
DAEMON_TOML = """[daq]
url = "modbus-tcp://192.168.1.50:502?unit=1"
timeout = 0.1
read_period = 0.5
unreachable_report = 30

[recording]
directory = "/var/lib/loopcal/recordings"
flush_period = 1.0
rotate_seconds = 3600
rotate_size = "256 MiB"
disk_budget = "20 GiB"
max_backlog_scans = 500000
compact = true
keep_views_days = 30

[controller]
config = "/etc/loopcal/controller/controller.toml"

[health]
enabled = true
false_alarm = 1e-8

[upkeep]
mode = "propose"
target_mm = 0.05
threshold_mm = 0.1
min_interval = 600
segment = 15

[metrics]
listen = "127.0.0.1:9108"

[live]
listen = "127.0.0.1:8765"

[control]
socket = "/run/loopcal/control.sock"
client_timeout = 30
"""


def closed_and_unclosed(rows: np.ndarray, directory: Path) -> dict[bool, bytes]:
    """The bytes of ``rows`` written (:func:`write_recording`, in ``directory``) as a closed
    (True) and as an unclosed, crashed (False) recording."""
    out = {}
    for closed in (True, False):
        path = directory / f"original-{closed}.mcap"
        write_recording(path, rows, close=closed)
        out[closed] = path.read_bytes()
    return out


def chunk_spans(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of every chunk record of an intact file, in file order (found by
    walking its records with the mcap library's stream reader)."""
    spans, pos = [], 8
    stream = io.BytesIO(data)
    stream.seek(8)
    records = StreamReader(stream, skip_magic=True, emit_chunks=True).records
    while True:
        try:
            record = next(records)
        except (StopIteration, EndOfFile):  # an unclosed file ends after its last record
            return spans
        end = stream.tell()  # the reader has consumed exactly this record
        if isinstance(record, Chunk):
            spans.append((pos, end - pos))
        if isinstance(record, DataEnd):
            return spans
        pos = end


# ---------------------------------------------------------------------------- mutations


def flip_bits(data: bytes, positions: list[int]) -> bytes:
    out = bytearray(data)
    for p in positions:
        out[(p // 8) % len(out)] ^= 1 << (p % 8)
    return bytes(out)


def truncate(data: bytes, at: int) -> bytes:
    return data[: at % (len(data) + 1)]


def zero_run(data: bytes, at: int, length: int) -> bytes:
    at %= len(data)
    out = bytearray(data)
    out[at : at + length] = bytes(len(out[at : at + length]))
    return bytes(out)


def zero_tail(data: bytes, keep: int, extra: int) -> bytes:
    """Power loss on ext4: the size grew, the last blocks are zeros."""
    keep %= len(data) + 1
    return data[:keep] + bytes(extra)


def duplicate_chunk(data: bytes, k: int) -> bytes:
    spans = chunk_spans(data)
    off, n = spans[k % len(spans)]
    return data[: off + n] + data[off : off + n] + data[off + n :]


def swap_chunks(data: bytes, k: int) -> bytes:
    spans = chunk_spans(data)
    if len(spans) < 2:
        return data
    i = k % (len(spans) - 1)
    (a, na), (b, nb) = spans[i], spans[i + 1]
    # both records (and the message indexes between them) keep their bytes, in swapped order
    middle = data[a + na : b]
    return data[:a] + data[b : b + nb] + middle + data[a : a + na] + data[b + nb :]


def bad_length(data: bytes, k: int, value: int) -> bytes:
    """Overwrite a chunk record's 8-byte length field."""
    spans = chunk_spans(data)
    off, _ = spans[k % len(spans)]
    out = bytearray(data)
    struct.pack_into("<Q", out, off + 1, value % (1 << 64))
    return bytes(out)


def overwrite(data: bytes, at: int, junk: bytes) -> bytes:
    at %= len(data)
    out = bytearray(data)
    out[at : at + len(junk)] = junk[: len(out) - at]
    return bytes(out)


def tear_chunk(path: Path, k: int, *, head: int = 50, tail: int = 5) -> bytes:
    """Zero chunk ``k`` (in file order) of the recording at ``path`` but for its first
    ``head`` and last ``tail`` bytes: its data torn, its record header intact. Writes the
    file back; returns its new bytes."""
    data = path.read_bytes()
    off, length = chunk_spans(data)[k]
    data = zero_run(data, off + head, length - head - tail)
    path.write_bytes(data)
    return data


MUTATIONS: dict[str, Callable[..., bytes]] = {
    "flip": flip_bits,
    "truncate": truncate,
    "zero_run": zero_run,
    "zero_tail": zero_tail,
    "dup_chunk": duplicate_chunk,
    "swap_chunks": swap_chunks,
    "bad_length": bad_length,
    "overwrite": overwrite,
}


# ---------------------------------------------------------------------------- verdicts


def identities(rows: np.ndarray) -> list[bytes]:
    """Each scan's fields as bytes (without the layout's padding, which copies leave
    undefined)."""
    packed = repack_fields(rows)
    raw, k = packed.tobytes(), packed.dtype.itemsize
    return [raw[i : i + k] for i in range(0, len(raw), k)]


def judge(original: np.ndarray, path: Path) -> str:
    """What ``read_recordings`` made of a damaged copy of ``original``:

    - "intact": every scan, once, no warning needed;
    - "reported": some scans missing or duplicates dropped, and the file's warning says so
      (or its note says it was not closed and was read up to its last intact chunk: a cut
      that falls exactly between two flushes looks like a recorder that stopped there);
    - "declared": it raised RecordingError (its documented error);
    - "silent loss": scans missing and no warning;
    - "duplicated": a scan returned twice;
    - "fabricated": a scan returned that was never written (a lie);
    - "undeclared: <type>": any other exception.
    """
    try:
        out = rec.read_recordings(path)
    except rec.RecordingError:
        return "declared"
    except Exception as exc:  # noqa: BLE001 - this is what the verdict is about
        return f"undeclared: {type(exc).__name__}: {exc}"[:200]
    got = identities(out.scans)
    if len(set(got)) != len(got):
        return "duplicated"
    known = set(identities(original))
    if not set(got) <= known:
        return "fabricated"
    said = bool(out.warnings) or any(f.note for f in out.files)
    if len(got) < len(known):
        return "reported" if said else "silent loss"
    return "reported" if out.warnings else "intact"


ACCEPTABLE = {"intact", "reported", "declared"}
