"""CDR encoding, vectorised: numpy dtypes laid out as the CDR of fixed-size ROS 2 messages,
and the ``/daq/scans`` blocks whose body is scan rows back to back."""

from __future__ import annotations

import struct
from collections.abc import Iterable
from typing import Any

import numpy as np

from ..scan_rows import SCAN_DTYPE
from .schemas import BASE_FRAME, CDR_LE, PLATE_FRAME

# CDR (little endian) of messages with fixed-size fields only, vectorised: a numpy dtype
# with each field at its CDR offset (aligned to its size, counted from the end of the
# 4-byte encapsulation header), so n messages encode with one tobytes().
_CDR_PRIMITIVES = {"bool": "?", "uint8": "u1", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
                   "int64": "<i8", "uint64": "<u8", "float32": "<f4", "float64": "<f8"}  # fmt: skip


def cdr_dtype(fields: Iterable[tuple[str, str, int]]) -> np.dtype:
    """The CDR layout of a flat message as a numpy dtype.

    fields: (name, ROS 2 primitive type, count) in message order; count > 1 is a fixed-size
    array. A type ``"string=TEXT"`` is a string field that always holds TEXT (it becomes
    two fields: ``NAME_len``, the CDR length prefix, and ``NAME``, the bytes and NUL).
    The dtype's itemsize is the message length (CDR pads nothing after the last field).
    """
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    pos = 0

    def add(name: str, fmt: Any, size: int, align: int) -> None:
        nonlocal pos
        pos = -(-pos // align) * align
        names.append(name)
        formats.append(fmt)
        offsets.append(pos)
        pos += size

    for name, typ, count in fields:
        if typ.startswith("string="):
            n = len(typ[7:].encode()) + 1
            add(name + "_len", "<u4", 4, 4)
            add(name, f"S{n}", n, 1)
            continue
        code = np.dtype(_CDR_PRIMITIVES[typ])
        add(name, (code, (count,)) if count > 1 else code, code.itemsize * count, code.itemsize)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": pos})


_TIME_FIELDS = [("sec", "int32", 1), ("nanosec", "uint32", 1)]
JOINT_STATE_DTYPE = cdr_dtype(
    [*_TIME_FIELDS, ("epoch", "uint32", 1), ("counter", "uint64", 1), ("volts", "float32", 4),
     ("lengths_mm", "float32", 4), ("channel_ok", "bool", 4), ("pose_ok", "bool", 1),
     ("euler_zyz_deg", "float32", 3), ("tilt_deg", "float32", 1), ("swivel_deg", "float32", 1),
     ("closure_rms_mm", "float32", 1)]
)  # fmt: skip
FRAME_TRANSFORM_DTYPE = cdr_dtype(
    [*_TIME_FIELDS, ("parent_frame_id", f"string={BASE_FRAME}", 1),
     ("child_frame_id", f"string={PLATE_FRAME}", 1), ("translation", "float64", 3),
     ("rotation", "float64", 4)]
)  # fmt: skip


def cdr_messages(arr: np.ndarray) -> list[bytes]:
    """One CDR message (encapsulation header + body) per element of a cdr_dtype array."""
    k = arr.dtype.itemsize
    body = np.ascontiguousarray(arr).tobytes()
    return [CDR_LE + body[i : i + k] for i in range(0, len(body), k)]


def fill_string_fields(arr: np.ndarray) -> None:
    for name in arr.dtype.names:
        if name + "_len" in arr.dtype.names:
            arr[name + "_len"] = arr.dtype[name].itemsize
            arr[name] = FRAME_TRANSFORM_CONSTANTS[name]


FRAME_TRANSFORM_CONSTANTS = {"parent_frame_id": BASE_FRAME.encode(),
                             "child_frame_id": PLATE_FRAME.encode()}  # fmt: skip


# ---------------------------------------------------------------------------- CDR blocks

# CDR little-endian encapsulation, then the sequence length; the first row's uint64 aligns
# to 8 bytes after the encapsulation header, so the rows start at byte 4 + 8.
_ROWS_AT = 4 + 8
# CDR does not pad a struct's tail: the last row ends at its last field.
_LAST_FIELD_END = max(
    SCAN_DTYPE.fields[name][1] + SCAN_DTYPE.fields[name][0].itemsize for name in SCAN_DTYPE.names
)
_TAIL = SCAN_DTYPE.itemsize - _LAST_FIELD_END


def encode_scan_block(rows: np.ndarray) -> bytes:
    """One ``loopcal_msgs/msg/ScanBlock`` message (CDR) holding ``rows`` (SCAN_DTYPE)."""
    rows = np.ascontiguousarray(rows, dtype=SCAN_DTYPE)
    if not len(rows):
        return CDR_LE + struct.pack("<I", 0)
    body = rows.tobytes()
    if _TAIL:
        body = body[:-_TAIL]
    return CDR_LE + struct.pack("<I4x", len(rows)) + body


def _block_count(data: bytes) -> int | str:
    """The number of scans a ``/daq/scans`` message holds, or why it is not a well-formed
    block (CDR little endian, a length that fits the count exactly)."""
    if len(data) < 8 or data[:4] != CDR_LE:
        return "scan block is not little-endian CDR"
    (n,) = struct.unpack_from("<I", data, 4)
    want = _ROWS_AT + n * SCAN_DTYPE.itemsize - _TAIL if n else 8
    if len(data) != want:
        return f"scan block of {n} scans has {len(data)} bytes, not {want}"
    return n


def _decode(messages: Iterable[bytes], *, strict: bool) -> tuple[np.ndarray, int]:
    """Rows and how many messages were not well-formed blocks (skipped; ``strict``: the
    first raises ValueError saying why)."""
    blocks, bad, total = [], 0, 0
    for data in messages:
        n = _block_count(data)
        if isinstance(n, str):
            if strict:
                raise ValueError(n)
            bad += 1
        elif n:
            blocks.append((data, n))
            total += n
    rows = np.zeros(total, dtype=SCAN_DTYPE)
    raw = memoryview(rows).cast("B")
    pos, size = 0, SCAN_DTYPE.itemsize
    for data, n in blocks:
        k = n * size - _TAIL
        raw[pos : pos + k] = memoryview(data)[_ROWS_AT : _ROWS_AT + k]
        pos += n * size
    return rows, bad


def decode_scan_blocks_checked(messages: Iterable[bytes]) -> tuple[np.ndarray, int]:
    """Rows (SCAN_DTYPE) of ``/daq/scans`` messages, in order, and how many messages were
    not well-formed blocks (skipped). Each block's body is copied once, straight into the
    rows (the last row of a block lacks CDR's trailing padding, which stays zero)."""
    return _decode(messages, strict=False)


def decode_scan_blocks(messages: Iterable[bytes]) -> np.ndarray:
    """Rows (SCAN_DTYPE) of ``/daq/scans`` messages, in order. Raises ValueError if one is
    not a well-formed block."""
    return _decode(messages, strict=True)[0]
