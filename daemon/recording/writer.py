"""Writing a recording file: header, schemas, channels and metadata, then one flush at a time
(the raw scans and events, then the views, then fsync), and the summary at close."""

from __future__ import annotations

import json
import logging
import os
import socket
import sys
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np
from mcap.writer import CompressionType, Writer

from loopcal.calibration.parameters import check_vector

from ..config.durable import fsync_dir
from ..events import Event
from ..scan_rows import SCAN_DTYPE
from ..times import now_text
from ..version import loopcal_version
from .cdr import encode_scan_block
from .schemas import (
    BLOCK_SPAN_NS,
    CHANNELS,
    FORMAT_VERSION,
    TOPIC_EVENTS,
    TOPIC_LOG,
    TOPIC_SCANS,
    TOPIC_SCENE,
    TOPIC_STATE,
    TOPIC_TRANSFORM,
    schema_bytes,
)
from .views import (
    WrittenViews,
    joint_states,
    scene_message,
    state_messages,
    transform_messages,
)

log = logging.getLogger(__name__)

#: chunks are closed by flushes only, never by size
_CHUNK_SIZE = 1 << 30

# ---------------------------------------------------------------------------- writer


class RecordingWriter:
    """One recording file being written.

    Creating it creates the file (never overwriting one), writes the header, schemas,
    channels and metadata, and makes them durable. :meth:`write` appends one flush: the raw
    scans and events, then the per-scan views, then fsync. :meth:`close` writes the summary
    and index. After an I/O error the writer is broken: call :meth:`abandon`, which cuts the
    file back to what was durable before (a valid recording without summary).

    path: the file to create. metadata: name -> {key: value} records to write at the start.
    params: the controller config's full parameter vector (20,), for the views.
    fsync: make each write durable (only synthetic test data turns it off; the layout is
    the same either way). on_views: called with each write's views (:class:`WrittenViews`)
    once they are in the file, from the writing thread (the recorder's live view); it must
    return at once, and what it raises is not the recording's concern (logged, ignored).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        metadata: dict[str, dict[str, str]],
        params: np.ndarray,
        compression: CompressionType = CompressionType.ZSTD,
        fsync: bool = True,
        on_views: Callable[[WrittenViews], None] | None = None,
    ) -> None:
        self.path = Path(path)
        self.on_views = on_views
        self._fsync = fsync
        self.params = check_vector(params).copy()
        self.scans_written = 0
        self.first_stamp_ns: int | None = None
        self.last_stamp_ns: int | None = None
        #: log time of the last event written (events' log times never go back in a file)
        self.last_event_ns: int | None = None
        self.durable_size = 0
        #: why the per-scan poses could not be computed ("" while they can); the raw scans
        #: are written regardless
        self.views_error = ""
        self._blocks = 0
        self._scene_done = False
        self._closed = False
        self._file = _DirectFile(self.path)
        try:
            # the data section's CRC (in the DataEnd record) covers what no other CRC does:
            # the header and the metadata records (loopcal verify checks it)
            self._writer = Writer(self._file, chunk_size=_CHUNK_SIZE, compression=compression,
                                  enable_crcs=True, enable_data_crcs=True)  # fmt: skip
            self._writer.start(profile="", library=f"loopcal {loopcal_version()}")
            self._channels: dict[str, int] = {}
            for topic, (schema, schema_enc, msg_enc) in CHANNELS.items():
                sid = self._writer.register_schema(schema, schema_enc, schema_bytes(schema))
                self._channels[topic] = self._writer.register_channel(topic, msg_enc, sid)
            for name, record in metadata.items():
                self._writer.add_metadata(name, {k: str(v) for k, v in record.items()})
            self._sync()
            fsync_dir(self.path.parent)
        except BaseException:
            self.abandon()
            if self.durable_size == 0:  # nothing of it was ever durable: leave no husk
                try:
                    self.path.unlink()
                except OSError:
                    pass
            raise

    @property
    def size(self) -> int:
        """Bytes in the file so far."""
        return self._file.tell()

    def _sync(self) -> None:
        if self._fsync:
            os.fsync(self._file.fileno())
        self.durable_size = self._file.tell()

    def write(self, rows: np.ndarray, events: Iterable[Event] = ()) -> None:
        """Append scans (SCAN_DTYPE rows, oldest first) and events, and make them durable.

        The scans' stamps are their log times as they are: the caller keeps them in order
        (the recorder starts a new file where they would go back). Events are written in
        time order, none logged before the last one already written.

        Raises OSError if the disk refuses; the writer must then be abandoned.
        """
        if self._closed:
            raise ValueError(f"{self.path}: recording already closed")
        rows = np.asarray(rows, dtype=SCAN_DTYPE)
        events = list(events)
        w, ch = self._writer, self._channels
        if len(rows):
            stamps = rows["stamp_ns"]
            cuts = np.flatnonzero(np.diff((stamps - stamps[0]) // BLOCK_SPAN_NS)) + 1
            for block in np.split(rows, cuts):
                w.add_message(ch[TOPIC_SCANS], int(block["stamp_ns"][0]),
                              encode_scan_block(block), int(block["host_ns"][-1]),
                              self._blocks & 0xFFFFFFFF)  # fmt: skip
                self._blocks += 1
        # Events come from several threads, each stamped when it happened, and reach a
        # flush in the order they were handed on, not quite in time order: written in time
        # order, each logged no earlier than the one before it in the file (its own time
        # stays in the message and its publish time).
        for ev in sorted(events, key=lambda e: e.stamp_ns):
            obj = ev.to_json()
            at = ev.stamp_ns
            if self.last_event_ns is not None and at < self.last_event_ns:
                at = self.last_event_ns
            self.last_event_ns = at
            w.add_message(ch[TOPIC_EVENTS], at, json.dumps(obj).encode(), ev.stamp_ns)
            w.add_message(ch[TOPIC_LOG], at, json.dumps(log_entry(ev, obj)).encode(), ev.stamp_ns)
        w.flush()  # chunk 1: what a reader of the scans needs
        if len(rows):
            self._write_views(rows)
            w.flush()  # chunk 2: the views
            self.scans_written += len(rows)
            if self.first_stamp_ns is None:
                self.first_stamp_ns = int(rows["stamp_ns"][0])
            self.last_stamp_ns = int(rows["stamp_ns"][-1])
        self._sync()

    def _write_views(self, rows: np.ndarray) -> None:
        w, ch = self._writer, self._channels
        js = joint_states(rows, self.params)
        if js.error and not self.views_error:
            self.views_error = js.error
        stamps, hosts = rows["stamp_ns"], rows["host_ns"]
        seq = rows["counter64"] & 0xFFFFFFFF
        if not self._scene_done:
            t0 = int(stamps[0])
            w.add_message(ch[TOPIC_SCENE], t0, scene_message(t0, self.params), t0)
            self._scene_done = True
        states = state_messages(rows, js)
        for i, data in enumerate(states):
            w.add_message(ch[TOPIC_STATE], int(stamps[i]), data, int(hosts[i]), int(seq[i]))
        good = np.flatnonzero(js.pose_ok)
        transforms = transform_messages(stamps[good], js.quat[good])
        for i, data in zip(good, transforms, strict=True):
            w.add_message(ch[TOPIC_TRANSFORM], int(stamps[i]), data, int(hosts[i]), int(seq[i]))
        if self.on_views is not None:
            try:
                self.on_views(WrittenViews(stamps.copy(), states, stamps[good], transforms))
            except Exception:  # noqa: BLE001 - a reader of the views never stops the recording
                log.exception("a listener of the views failed")

    def close(self) -> None:
        """Write the summary and index, fsync and close. Idempotent."""
        if self._closed:
            return
        self._writer.finish()
        self._sync()
        self._closed = True
        self._file.close()
        fsync_dir(self.path.parent)

    def abandon(self) -> None:
        """Give up on the file after an error: cut it back to the last durable size (a valid
        recording without summary) and close it. Never raises."""
        self._closed = True
        try:
            os.ftruncate(self._file.fileno(), self.durable_size)
            os.fsync(self._file.fileno())
        except (OSError, ValueError):
            pass
        self._file.close()


class _DirectFile:
    """An unbuffered binary file for the MCAP writer: every write goes to the kernel at once
    (whole or raising), so after an error nothing is left in a buffer to be written later."""

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o640)
        self._pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        while view:
            n = os.write(self._fd, view)
            self._pos += n
            view = view[n:]
        return len(data)

    def flush(self) -> None:
        pass

    def tell(self) -> int:
        return self._pos

    def fileno(self) -> int:
        return self._fd

    def close(self) -> None:
        if self._fd >= 0:
            try:
                os.close(self._fd)
            except OSError:
                pass
            self._fd = -1


def log_entry(ev: Event, obj: dict | None = None) -> dict:
    """An event as a ``foxglove.Log`` message (``/loopcal/log``; ``obj``: its ``to_json()``
    if already made)."""
    obj = ev.to_json() if obj is None else obj
    return {"timestamp": obj["timestamp"], "level": obj["level"], "name": "loopcal",
            "message": f"{ev.kind}: {ev.message}", "file": "", "line": 0}  # fmt: skip


def metadata_records(
    *,
    device: dict[str, str],
    controller: dict[str, str],
    command: str,
    extra: dict[str, str] | None = None,
) -> dict[str, dict[str, str]]:
    """The metadata records of a new recording file."""
    return {
        "loopcal": {
            "format": FORMAT_VERSION,
            "version": loopcal_version(),
            "hostname": socket.gethostname(),
            "pid": str(os.getpid()),
            "python": sys.version.split()[0],
            "command": command,
            "created_utc": now_text(),
            **(extra or {}),
        },
        "device": dict(device),
        "controller_config": dict(controller),
    }
