"""Real recordings, written by the daemon's own writer: a file of scan rows
(:func:`write_rows`, :func:`write_recording`), a directory of them as a recorder leaves it
(:func:`write_directory`), a copy compacted as the daemon keeps closed files
(:func:`compacted_copy`), a file in an older loopcal's layout (:func:`in_large_chunks`), and
what is not a recording, each with the words a command refuses it in
(:func:`not_recordings`)."""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from loopcal.calibration.parameters import NOMINAL
from loopcal.daemon import recording as rec
from loopcal.daemon.events import Event, Level
from loopcal.daemon.recording.compact import compact


def write_rows(
    path: Path,
    rows: np.ndarray,
    *,
    per: int = 20,
    events: list[Event] | tuple[Event, ...] = (),
    close: bool = True,
    metadata: dict[str, dict[str, str]] | None = None,
    params: np.ndarray = NOMINAL,
    fsync: bool = True,
) -> tuple[rec.RecordingWriter, list[int]]:
    """A recording of ``rows`` by the daemon's writer, ``per`` scans a flush. Each event is
    written with the flush whose scans' time holds it (from the flush's first scan, for at
    most a second): events outside every flush are not written, so one list can serve
    several files. Returns the writer (closed unless ``close`` is False) and the durable
    size after each flush."""
    if metadata is None:
        metadata = rec.metadata_records(
            device={"model": "LDQ412", "serial": "12648430"},
            controller={"path": "", "d01": "97.4"},
            command="pytest",
        )
    w = rec.RecordingWriter(path, metadata=metadata, params=params, fsync=fsync)
    stamps = rows["stamp_ns"].astype(np.int64)
    sizes = []
    for k in range(0, len(rows), per):
        lo = int(stamps[k])
        hi = lo + 10**9 if k + per >= len(rows) else min(lo + 10**9, int(stamps[k + per]))
        w.write(rows[k : k + per], [e for e in events if lo <= e.stamp_ns < hi])
        sizes.append(w.durable_size)
    if close:
        w.close()
    return w, sizes


def write_recording(path: Path, rows: np.ndarray, *, per: int = 20, close: bool = True,
                    events: bool = True) -> list[int]:  # fmt: skip
    """:func:`write_rows` with an event every 100 scans; returns the durable size after
    each flush."""
    evs = [
        Event(int(rows["stamp_ns"][k]), "gap", Level.WARNING, f"test {k}", {"k": k})
        for k in range(0, len(rows), per)
        if events and k % 100 == 0
    ]
    return write_rows(path, rows, per=per, events=evs, close=close)[1]


def write_directory(
    directory: Path,
    rows: np.ndarray,
    *,
    rate: int = 20,
    per: int | None = None,
    scans_per_file: int | None = None,
    command: str = "tests",
) -> Path:
    """``rows`` as a recorder leaves them in ``directory``: files named by their first
    scan's stamp, ``scans_per_file`` scans each (default: one file), ``per`` scans a flush
    (default ``rate``: a flush a second), metadata naming an LDQ-412 at ``rate`` Hz, not
    fsynced. Returns ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    meta = rec.metadata_records(
        device={"model": "LDQ412", "scan_rate_hz": str(rate)}, controller={}, command=command
    )
    step = scans_per_file or max(len(rows), 1)
    for a in range(0, len(rows), step):
        part = rows[a : a + step]
        write_rows(directory / rec.recording_name(int(part["stamp_ns"][0])), part,
                   per=per or rate, metadata=meta, fsync=False)  # fmt: skip
    return directory


def read_scans(directory: Path) -> np.ndarray:
    """Every scan of the recording in ``directory``."""
    return rec.read_recordings(directory).scans


def compacted_copy(
    directory: Path, kept: Path | None = None, *, reuse: bool = False
) -> tuple[Path, float]:
    """A copy of the recording ``directory`` as the daemon keeps it: every closed file
    compacted, as after its rotation. The copy goes to ``kept`` (by default
    DIRECTORY-compacted beside it), replacing one already there, or, with ``reuse``, one
    already there is taken as it is. Returns the copy and the seconds compacting took (0
    for a copy reused)."""
    kept = kept or directory.with_name(directory.name + "-compacted")
    if kept.is_dir():
        if reuse and rec.find_recordings(kept):
            return kept, 0.0
        if not reuse:
            shutil.rmtree(kept)
    shutil.copytree(directory, kept, dirs_exist_ok=True)
    t = time.perf_counter()
    for f in rec.find_recordings(kept):
        if not compact(f).done:
            raise SystemExit(f"could not compact {f}")
    return kept, time.perf_counter() - t


def in_large_chunks(src: Path, dst: Path, edit: Callable[[dict[str, str]], None]) -> None:
    """``src`` rewritten as the first loopcal that compacted did: the same schemas, channels
    and messages in file order, in chunks of 4 MiB, its ``loopcal`` metadata record changed
    by ``edit`` (in place)."""
    with open(src, "rb") as f, open(dst, "wb") as out:
        reader = make_reader(f)
        header, summary = reader.get_header(), reader.get_summary()
        w = Writer(out, chunk_size=4 << 20, compression=CompressionType.ZSTD)
        w.start(profile=header.profile, library=header.library)
        sids = {sid: w.register_schema(s.name, s.encoding, s.data)
                for sid, s in sorted(summary.schemas.items())}  # fmt: skip
        for _, c in sorted(summary.channels.items()):
            w.register_channel(c.topic, c.message_encoding, sids[c.schema_id], dict(c.metadata))
        for m in reader.iter_metadata():
            record = dict(m.metadata)
            if m.name == "loopcal":
                edit(record)
            w.add_metadata(m.name, record)
        for _, c, m in reader.iter_messages(log_time_order=False):
            w.add_message(c.id, m.log_time, m.data, m.publish_time, m.sequence)
        w.finish()


def not_recordings(tmp_path: Path) -> list[tuple[list[str | Path], str]]:
    """What a command that takes recordings must refuse as bad input, made under
    ``tmp_path`` (a text file named ``x.mcap``, an empty directory, a FIFO named
    ``fifo.mcap``), each as (the command's arguments, the words its error names it in)."""
    text = tmp_path / "x.mcap"
    text.write_text("root:x:0:0:root:/root:/bin/bash\n")
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    fifo = tmp_path / "fifo.mcap"
    os.mkfifo(fifo)
    missing = tmp_path / "missing.mcap"
    return [
        (["/etc/passwd"], "/etc/passwd: not an MCAP file"),
        ([""], "an empty path"),
        (["/dev/zero"], "/dev/zero: not a regular file (a character device)"),
        ([fifo], f"{fifo}: not a regular file (a FIFO)"),
        ([empty_dir], f"{empty_dir}: no recordings"),
        ([text], f"{text}: not an MCAP file"),
        ([missing], f"{missing}: no such file"),
    ]
