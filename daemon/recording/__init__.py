"""The recording format: MCAP files of raw scans, derived plate poses and events.

One recording file holds, for a stretch of time (see docs/recording.md for the full table):

========================  =======================================  =========  ==============
topic                     schema                                   encoding   rate
========================  =======================================  =========  ==============
``/daq/scans``            ``loopcal_msgs/msg/ScanBlock`` (ros2msg)  cdr        one per flush
``/loopcal/events``       ``loopcal.Event`` (jsonschema)           json       when it happens
``/loopcal/log``          ``foxglove.Log`` (jsonschema)            json       when it happens
``/joint/state``          ``loopcal_msgs/msg/JointState``           cdr        every scan
``/plate/transform``      ``foxglove_msgs/msg/FrameTransform``      cdr        every good scan
``/plate/scene``          ``foxglove.SceneUpdate`` (jsonschema)    json       once per file
========================  =======================================  =========  ==============

plus metadata records ``loopcal`` (version, host, command), ``device`` (what the DAQ said it
is) and ``controller_config`` (the parameters the poses were computed with).

``/daq/scans`` is the record: every scan exactly once, raw and lossless, in blocks of at most
one flush period (about one second). The other channels are views for people: Foxglove plots
``/joint/state`` (volts and lengths of every channel) at the full scan rate and its 3D panel
moves the plate frame of ``/plate/transform``.

Layout, chosen for crash safety and for fast reading: every flush (about once per second)
writes two chunks, first the raw block with any events, then the per-scan views, and fsyncs.
A reader that only wants the scans skips the view chunks by the chunk index, and decodes each
block with one ``numpy.frombuffer``: the block's CDR body is the rows of
:data:`daemon.scans.SCAN_DTYPE` back to back. A file cut short by a crash or a power loss
still reads back up to its last complete chunk.
"""

from __future__ import annotations

import json
import os
import re
import socket
import struct
import sys
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Channel, Metadata, Statistics
from mcap.writer import CompressionType, Writer
from scipy.spatial.transform import Rotation

from calibration.kinematics import (
    base_points,
    euler_zyz,
    forward_kinematics,
    plate_home,
    volts_to_lengths,
)
from calibration.parameters import check_vector

from .. import scans as scan_rows
from ..events import Event
from ..scans import SCAN_DTYPE, SCAN_FIELDS
from .records import (
    FOOTER_BYTES,
    MAGIC,
    PARSE_ERRORS,
    RECORD_HEAD,
    ChunkRecords,
    Damage,
    Summary,
    parse_record,
    read_chunk,
    read_header,
    read_statistics,
    read_summary,
    record_at,
    walk,
)

FORMAT_VERSION = "1"

TOPIC_SCANS = "/daq/scans"
TOPIC_EVENTS = "/loopcal/events"
TOPIC_LOG = "/loopcal/log"
TOPIC_STATE = "/joint/state"
TOPIC_TRANSFORM = "/plate/transform"
TOPIC_SCENE = "/plate/scene"

SCAN_BLOCK_SCHEMA = "loopcal_msgs/msg/ScanBlock"
JOINT_STATE_SCHEMA = "loopcal_msgs/msg/JointState"
FRAME_TRANSFORM_SCHEMA = "foxglove_msgs/msg/FrameTransform"
BASE_FRAME, PLATE_FRAME = "base", "plate"

_CDR_LE = b"\x00\x01\x00\x00"  # CDR encapsulation header: little endian, no options
#: a raw block never spans more stamp time than this (readers widen time windows by it)
BLOCK_SPAN_NS = 1_000_000_000
#: chunks are closed by flushes only, never by size
_CHUNK_SIZE = 1 << 30
_NS = 1_000_000_000
_NAME_RE = re.compile(r"^loopcal-(\d{8}T\d{6}\.\d{6})Z\.mcap$")


class RecordingError(Exception):
    """A file cannot be read as a loopcal recording; the message names the file and why."""


def loopcal_version() -> str:
    try:
        return importlib_metadata.version("loopcal")
    except importlib_metadata.PackageNotFoundError:  # running from a bare checkout
        return "0+unknown"


# ---------------------------------------------------------------------------- schemas

_ROS_TYPES = {"uint64": "uint64", "int64": "int64", "uint32": "uint32", "uint16": "uint16",
              "bool": "bool"}  # fmt: skip


def scan_block_msgdef() -> str:
    """The ROS 2 message definition of ``/daq/scans`` (``ros2msg`` schema text)."""
    lines = [
        "# LDQ-412 scans exactly as the driver delivered them, raw and lossless, oldest first.",
        "# Every scan of the recording is in exactly one block.",
        "loopcal_msgs/Scan[] scans",
        "=" * 80,
        "MSG: loopcal_msgs/Scan",
    ]
    for name, kind, count, meaning in SCAN_FIELDS:
        typ = _ROS_TYPES[kind] + (f"[{count}]" if count > 1 else "")
        lines.append(f"{typ} {name}  # {meaning}")
    return "\n".join(lines) + "\n"


def _time_schema(description: str) -> dict[str, Any]:
    return {
        "type": "object",
        "title": "time",
        "description": description,
        "properties": {
            "sec": {"type": "integer", "minimum": 0},
            "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
        },
    }


def _xyz(title: str, keys: str) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": {k: {"type": "number"} for k in keys}}


_STRING = {"type": "string"}


def _object(title: str, **properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": properties}


def _array(items: dict[str, Any], n: int | None = None) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "array", "items": items}
    if n is not None:
        out["minItems"] = out["maxItems"] = n
    return out


_NUMBER = {"type": "number"}

JSON_SCHEMAS: dict[str, dict[str, Any]] = {
    "loopcal.Event": {
        "title": "loopcal.Event",
        "description": "Something that happened to the acquisition (docs/recording.md lists kinds)",
        "type": "object",
        "properties": {
            "timestamp": _time_schema("when it happened (UTC)"),
            "kind": {"type": "string", "description": "event kind, e.g. gap, restart"},
            "level": {"type": "integer", "description": "1 debug, 2 info, 3 warning, 4 error"},
            "message": {"type": "string", "description": "one line for people"},
            # Foxglove's schema parser needs "properties" on every object, even a free one
            "details": {"type": "object", "properties": {}, "description": "facts for programs"},
        },
    },
    "foxglove.Log": {
        "title": "foxglove.Log",
        "description": "A log message",
        "type": "object",
        "properties": {
            "timestamp": _time_schema("Timestamp of log message"),
            "level": {"type": "integer", "description": "1 debug ... 5 fatal"},
            "message": {"type": "string"},
            "name": {"type": "string"},
            "file": {"type": "string"},
            "line": {"type": "integer", "minimum": 0},
        },
    },
}


def _scene_schema() -> dict[str, Any]:
    pose = {
        "title": "foxglove.Pose",
        "type": "object",
        "properties": {
            "position": _xyz("foxglove.Vector3", "xyz"),
            "orientation": _xyz("foxglove.Quaternion", "xyzw"),
        },
    }
    color = _xyz("foxglove.Color", "rgba")
    point = _xyz("foxglove.Point3", "xyz")
    size = _xyz("foxglove.Vector3", "xyz")
    sphere = {"type": "object", "properties": {"pose": pose, "size": size, "color": color}}
    line = {
        "type": "object",
        "properties": {
            "type": {"type": "integer", "description": "0 strip, 1 loop, 2 list"},
            "pose": pose,
            "thickness": _NUMBER,
            "scale_invariant": {"type": "boolean"},
            "points": _array(point),
            "color": color,
            "colors": _array(color),
            "indices": _array({"type": "integer"}),
        },
    }
    text = {
        "type": "object",
        "properties": {"pose": pose, "billboard": {"type": "boolean"}, "font_size": _NUMBER,
                       "scale_invariant": {"type": "boolean"}, "color": color,
                       "text": {"type": "string"}},
    }  # fmt: skip
    duration = {"type": "object", "properties": {"sec": {"type": "integer"},
                                                 "nsec": {"type": "integer"}}}  # fmt: skip
    entity = {
        "type": "object",
        "properties": {
            "timestamp": _time_schema("Timestamp of the entity"),
            "frame_id": {"type": "string"},
            "id": {"type": "string"},
            "lifetime": duration,
            "frame_locked": {"type": "boolean"},
            "metadata": _array(_object("foxglove.KeyValuePair", key=_STRING, value=_STRING)),
            **{k: _array({"type": "object", "properties": {}}) for k in
               ("arrows", "cubes", "cylinders", "triangles", "models")},
            "spheres": _array(sphere),
            "lines": _array(line),
            "texts": _array(text),
        },
    }  # fmt: skip
    return {
        "title": "foxglove.SceneUpdate",
        "description": "An update to the entities displayed in a 3D scene",
        "type": "object",
        "properties": {
            "deletions": _array(
                _object(
                    "foxglove.SceneEntityDeletion",
                    timestamp=_time_schema("Timestamp of the deletion"),
                    type={"type": "integer", "description": "0 matching id, 1 all"},
                    id=_STRING,
                )
            ),
            "entities": _array(entity),
        },
    }


JSON_SCHEMAS["foxglove.SceneUpdate"] = _scene_schema()

#: topic -> (schema name, schema encoding, message encoding)
CHANNELS: dict[str, tuple[str, str, str]] = {
    TOPIC_SCANS: (SCAN_BLOCK_SCHEMA, "ros2msg", "cdr"),
    TOPIC_EVENTS: ("loopcal.Event", "jsonschema", "json"),
    TOPIC_LOG: ("foxglove.Log", "jsonschema", "json"),
    TOPIC_STATE: (JOINT_STATE_SCHEMA, "ros2msg", "cdr"),
    TOPIC_TRANSFORM: (FRAME_TRANSFORM_SCHEMA, "ros2msg", "cdr"),
    TOPIC_SCENE: ("foxglove.SceneUpdate", "jsonschema", "json"),
}


def _schema_bytes(name: str) -> bytes:
    if name == SCAN_BLOCK_SCHEMA:
        return scan_block_msgdef().encode()
    if name in _MSGDEFS:
        return _MSGDEFS[name].encode()
    return json.dumps(JSON_SCHEMAS[name], indent=1).encode()


_SEP = "=" * 80
_TIME_MSG = f"{_SEP}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
_MSGDEFS = {
    JOINT_STATE_SCHEMA: (
        "# One scan seen through the controller config in force (NaN where there is no pose).\n"
        "builtin_interfaces/Time timestamp  # estimated acquisition time of the scan (UTC)\n"
        "uint32 epoch  # power-on epoch of the module as recorded\n"
        "uint64 counter  # scans since the module's power-on\n"
        "float32[4] volts  # channel 1..4, V\n"
        "float32[4] lengths_mm  # actuator 1..4 length d = S V + d0, mm\n"
        "bool[4] channel_ok  # channel neither at the rail nor faulted\n"
        "bool pose_ok  # forward kinematics converged on four good channels\n"
        "float32[3] euler_zyz_deg  # plate orientation, intrinsic Z-Y-Z Euler angles, deg\n"
        "float32 tilt_deg  # output axis away from +z, deg\n"
        "float32 swivel_deg  # rotation about the output axis, deg\n"
        "float32 closure_rms_mm  # RMS misfit of the four lengths at the pose (loop closure)\n"
        + _TIME_MSG
    ),
    FRAME_TRANSFORM_SCHEMA: (
        "builtin_interfaces/Time timestamp\n"
        "string parent_frame_id\n"
        "string child_frame_id\n"
        "geometry_msgs/Vector3 translation\n"
        "geometry_msgs/Quaternion rotation\n"
        + _TIME_MSG
        + f"{_SEP}\nMSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
        + f"{_SEP}\nMSG: geometry_msgs/Quaternion\n"
        "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
    ),
}

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
    return [_CDR_LE + body[i : i + k] for i in range(0, len(body), k)]


def _fill_strings(arr: np.ndarray) -> None:
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
        return _CDR_LE + struct.pack("<I", 0)
    body = rows.tobytes()
    if _TAIL:
        body = body[:-_TAIL]
    return _CDR_LE + struct.pack("<I4x", len(rows)) + body


def _block_rows(data: bytes) -> bytes | None:
    """The rows of one ``/daq/scans`` message as SCAN_DTYPE bytes, or None if it is not a
    well-formed block."""
    if len(data) < 8 or data[:4] != _CDR_LE:
        return None
    (n,) = struct.unpack_from("<I", data, 4)
    if len(data) != (_ROWS_AT + n * SCAN_DTYPE.itemsize - _TAIL if n else 8):
        return None
    return data[_ROWS_AT:] + _PAD if n else b""


_PAD = b"\x00" * _TAIL


def decode_scan_blocks_checked(messages: Iterable[bytes]) -> tuple[np.ndarray, int]:
    """Rows (SCAN_DTYPE) of ``/daq/scans`` messages, in order, and how many messages were
    not well-formed blocks (skipped)."""
    parts = [_block_rows(data) for data in messages]
    good = [p for p in parts if p is not None]
    rows = np.frombuffer(b"".join(good), dtype=SCAN_DTYPE).copy()
    return rows, len(parts) - len(good)


def decode_scan_blocks(messages: Iterable[bytes]) -> np.ndarray:
    """Rows (SCAN_DTYPE) of ``/daq/scans`` messages, in order. Raises ValueError if one is
    not a well-formed block."""
    messages = list(messages)
    rows, bad = decode_scan_blocks_checked(messages)
    if bad:
        first = next(m for m in messages if _block_rows(m) is None)
        if first[:4] != _CDR_LE or len(first) < 8:
            raise ValueError("scan block is not little-endian CDR")
        (n,) = struct.unpack_from("<I", first, 4)
        raise ValueError(f"scan block of {n} scans has {len(first)} bytes, not "
                         f"{_ROWS_AT + n * SCAN_DTYPE.itemsize - _TAIL if n else 8}")  # fmt: skip
    return rows


# ---------------------------------------------------------------------------- views


def _stamp(ns: int) -> dict[str, int]:
    sec, nsec = divmod(int(ns), _NS)
    return {"sec": sec, "nsec": nsec}


@dataclass(frozen=True)
class JointStates:
    """Per-scan views of n scans at one parameter vector (all arrays have n rows).

    volts (n, 4) V; lengths (n, 4) mm; channel_ok (n, 4); pose_ok (n,); quat (n, 4) as
    x, y, z, w (NaN where not pose_ok); euler_deg (n, 3); tilt_deg, swivel_deg,
    closure_rms_mm (n,). error: why no pose could be computed at all ("" normally).
    """

    volts: np.ndarray
    lengths: np.ndarray
    channel_ok: np.ndarray
    pose_ok: np.ndarray
    quat: np.ndarray
    euler_deg: np.ndarray
    tilt_deg: np.ndarray
    swivel_deg: np.ndarray
    closure_rms_mm: np.ndarray
    error: str = ""


def joint_states(rows: np.ndarray, params: np.ndarray) -> JointStates:
    """Volts, lengths and the plate orientation (forward kinematics) of each scan.

    rows: SCAN_DTYPE (n,); params: the full parameter vector (20,) of the controller config.
    Only scans whose four channels are trustworthy get a pose. If forward kinematics fails
    altogether (parameters that describe no mechanism), no scan gets one and ``error`` says
    why: the views must never stop the raw scans from being recorded.
    """
    n = len(rows)
    v = scan_rows.volts(rows)
    lengths = volts_to_lengths(v, params)
    ok = scan_rows.trustworthy(rows)
    quat = np.full((n, 4), np.nan)
    euler = np.full((n, 3), np.nan)
    rms = np.full(n, np.nan)
    pose_ok = np.zeros(n, dtype=bool)
    idx = np.flatnonzero(ok.all(axis=1) & np.isfinite(lengths).all(axis=1))
    error = ""
    if idx.size:
        try:
            with np.errstate(all="ignore"):
                fk = forward_kinematics(lengths[idx], params)
        except Exception as exc:  # noqa: BLE001 - reported in ``error``, never raised
            error = f"{type(exc).__name__}: {exc}"
            idx = idx[:0]
    if idx.size:
        good = fk.converged & np.isfinite(fk.rotations).all(axis=(1, 2))
        sel = idx[good]
        if sel.size:
            R = fk.rotations[good]
            quat[sel] = Rotation.from_matrix(R).as_quat()
            euler[sel] = np.degrees(euler_zyz(R))
            rms[sel] = fk.rms_mm[good]
            pose_ok[sel] = True
    a, b, g = euler.T
    swivel = np.degrees(np.angle(np.exp(1j * np.radians(a + g))))
    return JointStates(v, lengths, ok, pose_ok, quat, euler, b, swivel, rms, error)


def _secs(stamps: np.ndarray, arr: np.ndarray) -> None:
    sec, nsec = np.divmod(stamps.astype(np.int64), _NS)
    arr["sec"], arr["nanosec"] = sec, nsec


def state_messages(rows: np.ndarray, js: JointStates) -> list[bytes]:
    """``/joint/state`` messages (CDR) for n scans and their views."""
    arr = np.zeros(len(rows), dtype=JOINT_STATE_DTYPE)
    _secs(rows["stamp_ns"], arr)
    arr["epoch"] = rows["epoch"]
    arr["counter"] = rows["counter64"]
    arr["volts"] = js.volts
    arr["lengths_mm"] = js.lengths
    arr["channel_ok"] = js.channel_ok
    arr["pose_ok"] = js.pose_ok
    arr["euler_zyz_deg"] = js.euler_deg
    arr["tilt_deg"] = js.tilt_deg
    arr["swivel_deg"] = js.swivel_deg
    arr["closure_rms_mm"] = js.closure_rms_mm
    return cdr_messages(arr)


def transform_messages(stamps: np.ndarray, quat: np.ndarray) -> list[bytes]:
    """``/plate/transform`` messages (CDR): the plate frame rotated about the base origin.

    The quaternions are rounded to float32 precision (1e-7, far below what four 12-bit
    channels resolve) so that the recording compresses."""
    arr = np.zeros(len(stamps), dtype=FRAME_TRANSFORM_DTYPE)
    _secs(stamps, arr)
    _fill_strings(arr)
    arr["rotation"] = quat.astype(np.float32)
    return cdr_messages(arr)


def _scene_message(stamp_ns: int, params: np.ndarray) -> bytes:
    """The mechanism for Foxglove's 3D panel, in metres: base points A1..A4 fixed in the base
    frame; the plate's B1, B2 and the triangle O-B1-B2 locked to the plate frame."""
    ident = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}

    def pose(p: np.ndarray) -> dict[str, Any]:
        x, y, z = (float(c) / 1000.0 for c in p)
        return {"position": {"x": x, "y": y, "z": z}, "orientation": ident}

    def color(r: float, g: float, b: float) -> dict[str, float]:
        return {"r": r, "g": g, "b": b, "a": 1.0}

    def sphere(p: np.ndarray, c: dict[str, float]) -> dict[str, Any]:
        return {"pose": pose(p), "size": {"x": 0.012, "y": 0.012, "z": 0.012}, "color": c}

    def label(p: np.ndarray, text: str) -> dict[str, Any]:
        return {"pose": pose(p + np.array([0.0, 0.0, 8.0])), "billboard": True, "font_size": 14,
                "scale_invariant": True, "color": color(1, 1, 1), "text": text}  # fmt: skip

    def entity(frame: str, ident_: str, **prims: list) -> dict[str, Any]:
        out = {"timestamp": _stamp(stamp_ns), "frame_id": frame, "id": ident_,
               "lifetime": {"sec": 0, "nsec": 0}, "frame_locked": True, "metadata": []}  # fmt: skip
        for k in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts",
                  "models"):  # fmt: skip
            out[k] = prims.get(k, [])
        return out

    A = base_points(params)
    B = plate_home(params)
    origin = np.zeros(3)
    tri = [origin, B[0], B[1]]
    msg = {
        "deletions": [],
        "entities": [
            entity(BASE_FRAME, "base",
                   spheres=[sphere(a, color(0.2, 0.6, 1.0)) for a in A],
                   texts=[label(a, f"A{i + 1}") for i, a in enumerate(A)]),
            entity(PLATE_FRAME, "plate",
                   spheres=[sphere(b, color(1.0, 0.5, 0.1)) for b in B],
                   lines=[{"type": 1, "pose": pose(origin), "thickness": 3.0,
                           "scale_invariant": True,
                           "points": [pose(p)["position"] for p in tri],
                           "color": color(1.0, 0.5, 0.1), "colors": [], "indices": []}],
                   texts=[label(B[0], "B1"), label(B[1], "B2")]),
        ],
    }  # fmt: skip
    return json.dumps(msg, separators=(",", ":")).encode()


# ---------------------------------------------------------------------------- names


def recording_name(utc_ns: int) -> str:
    """``loopcal-YYYYmmddTHHMMSS.ffffffZ.mcap``: names sort by the UTC time they start."""
    sec, ns = divmod(int(utc_ns), _NS)
    t = datetime.fromtimestamp(sec, UTC)
    return f"loopcal-{t:%Y%m%dT%H%M%S}.{ns // 1000:06d}Z.mcap"


def name_time_ns(path: str | os.PathLike) -> int | None:
    """The UTC start time a recording's name gives, ns, or None if not a recording name."""
    m = _NAME_RE.match(Path(path).name)
    if not m:
        return None
    t = datetime.strptime(m.group(1), "%Y%m%dT%H%M%S.%f").replace(tzinfo=UTC)
    return int(t.timestamp()) * _NS + t.microsecond * 1000


def find_recordings(directory: str | os.PathLike) -> list[Path]:
    """The recordings in a directory (by their names), oldest first."""
    d = Path(directory)
    if not d.is_dir():
        raise RecordingError(f"{d}: not a directory")
    return sorted(p for p in d.iterdir() if _NAME_RE.match(p.name) and p.is_file())


# ---------------------------------------------------------------------------- writer


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


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
    the same either way).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        metadata: dict[str, dict[str, str]],
        params: np.ndarray,
        compression: CompressionType = CompressionType.ZSTD,
        fsync: bool = True,
    ) -> None:
        self.path = Path(path)
        self._fsync = fsync
        self.params = check_vector(params).copy()
        self.scans_written = 0
        self.first_stamp_ns: int | None = None
        self.last_stamp_ns: int | None = None
        self.durable_size = 0
        #: why the per-scan poses could not be computed ("" while they can); the raw scans
        #: are written regardless
        self.views_error = ""
        self._blocks = 0
        self._scene_done = False
        self._closed = False
        self._file = _DirectFile(self.path)
        try:
            self._writer = Writer(
                self._file, chunk_size=_CHUNK_SIZE, compression=compression, enable_crcs=True
            )
            self._writer.start(profile="", library=f"loopcal {loopcal_version()}")
            self._channels: dict[str, int] = {}
            for topic, (schema, schema_enc, msg_enc) in CHANNELS.items():
                sid = self._writer.register_schema(schema, schema_enc, _schema_bytes(schema))
                self._channels[topic] = self._writer.register_channel(topic, msg_enc, sid)
            for name, record in metadata.items():
                self._writer.add_metadata(name, {k: str(v) for k, v in record.items()})
            self._sync()
            _fsync_dir(self.path.parent)
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
        for ev in events:
            obj = ev.to_json()
            w.add_message(ch[TOPIC_EVENTS], ev.stamp_ns, json.dumps(obj).encode(), ev.stamp_ns)
            log = {"timestamp": obj["timestamp"], "level": obj["level"], "name": "loopcal",
                   "message": f"{ev.kind}: {ev.message}", "file": "", "line": 0}  # fmt: skip
            w.add_message(ch[TOPIC_LOG], ev.stamp_ns, json.dumps(log).encode(), ev.stamp_ns)
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
            w.add_message(ch[TOPIC_SCENE], t0, _scene_message(t0, self.params), t0)
            self._scene_done = True
        for i, data in enumerate(state_messages(rows, js)):
            w.add_message(ch[TOPIC_STATE], int(stamps[i]), data, int(hosts[i]), int(seq[i]))
        good = np.flatnonzero(js.pose_ok)
        for i, data in zip(good, transform_messages(stamps[good], js.quat[good]), strict=True):
            w.add_message(ch[TOPIC_TRANSFORM], int(stamps[i]), data, int(hosts[i]), int(seq[i]))

    def close(self) -> None:
        """Write the summary and index, fsync and close. Idempotent."""
        if self._closed:
            return
        self._writer.finish()
        self._sync()
        self._closed = True
        self._file.close()
        _fsync_dir(self.path.parent)

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
            "created_utc": datetime.now(UTC).isoformat(timespec="microseconds"),
            **(extra or {}),
        },
        "device": dict(device),
        "controller_config": dict(controller),
    }


# ---------------------------------------------------------------------------- reader


@dataclass(frozen=True)
class Loss:
    """Scans a file should hold and does not: a counter gap between two of its scans that
    no recorded ``missed`` count explains (a damaged or missing chunk).

    epoch: the power-on epoch. first: counter64 of the first missing scan. count: how many.
    after_ns, before_ns: stamps of the scans on either side.
    """

    epoch: int
    first: int
    count: int
    after_ns: int
    before_ns: int


@dataclass
class RecordingFile:
    """What one file of a recording held, and what of it could not be read.

    complete: closed normally (summary and index present and intact).
    scans: scans read from it (within the time window, duplicates dropped).
    first_stamp_ns, last_stamp_ns: the first and last scan's stamps, or None.
    metadata: name -> {key: value}.
    note: how the file was read when it was not closed normally (empty for a complete one).
    damage: the parts that could not be trusted (byte ranges, what was wrong, the time span
        of the messages they held where known).
    lost: scans known to be missing from the file (counter gaps no ``missed`` explains).
    duplicates: scans that appeared more than once (each is returned once).
    bad_messages: scan blocks or events inside intact chunks that did not decode.
    """

    path: Path
    complete: bool
    scans: int = 0
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    note: str = ""
    damage: list[Damage] = field(default_factory=list)
    lost: list[Loss] = field(default_factory=list)
    duplicates: int = 0
    bad_messages: int = 0
    #: byte offset of the last intact chunk that held scans (-1: none)
    last_scan_chunk: int = -1

    @property
    def lost_scans(self) -> int:
        """How many scans are known to be missing (see :attr:`lost`)."""
        return sum(x.count for x in self.lost)

    @property
    def intact(self) -> bool:
        """Nothing damaged, missing or duplicated."""
        return not (self.damage or self.lost or self.duplicates or self.bad_messages)

    @property
    def warning(self) -> str:
        """One line naming the file and what of it was lost, or "" if it read intact."""
        if self.intact:
            return ""
        parts: list[str] = []
        if self.lost:
            spans = ", ".join(
                f"counters {x.first}-{x.first + x.count - 1} of epoch {x.epoch} "
                f"({_utc(x.after_ns)} to {_utc(x.before_ns)})"
                for x in self.lost[:3]
            )
            more = f" and {len(self.lost) - 3} more gap(s)" if len(self.lost) > 3 else ""
            parts.append(f"{self.lost_scans} scan(s) missing: {spans}{more}")
        tail = [d for d in self.damage if self._after_last_scan(d)]
        if tail:
            d = tail[0]
            span = f" (messages of {_utc(d.start_ns)} to {_utc(d.end_ns)})" if d.end_ns else ""
            parts.append(f"the scans after {_utc(self.last_stamp_ns)} are lost: {d.what} at "
                         f"byte {d.offset}{span}" if self.last_stamp_ns is not None else
                         f"no scan could be read: {d.what} at byte {d.offset}{span}")  # fmt: skip
        inner = [d for d in self.damage if d not in tail]
        if inner:
            what = "; ".join(f"{d.what} at byte {d.offset}" for d in inner[:3])
            more = f"; {len(inner) - 3} more" if len(inner) > 3 else ""
            cost = "" if self.lost else " (no scan missing around them)"
            parts.append(f"{len(inner)} damaged part(s): {what}{more}{cost}")
        if self.duplicates:
            parts.append(f"{self.duplicates} duplicated scan(s) dropped (each kept once)")
        if self.bad_messages:
            parts.append(f"{self.bad_messages} undecodable message(s) skipped")
        return f"{self.path}: " + "; ".join(parts)

    def _after_last_scan(self, d: Damage) -> bool:
        return d.offset > self.last_scan_chunk


@dataclass
class Recording:
    """Scans and events of one or several recording files, oldest first.

    scans: SCAN_DTYPE rows (n,), each scan once (a scan in two files is kept once).
    events: events, in time order.
    files: one entry per file read.
    """

    scans: np.ndarray
    events: list[Event]
    files: list[RecordingFile]

    def __len__(self) -> int:
        return len(self.scans)

    @property
    def volts(self) -> np.ndarray:
        """(n, 4) channel voltages, V (mid-code reconstruction)."""
        return scan_rows.volts(self.scans)

    @property
    def stamp_s(self) -> np.ndarray:
        """(n,) acquisition times, s since the Unix epoch."""
        return self.scans["stamp_ns"] * 1e-9

    @property
    def warnings(self) -> list[str]:
        """One line per damaged or partly read file, naming it and what was lost."""
        return [f.warning for f in self.files if f.warning]

    def events_of(self, kind: str) -> list[Event]:
        return [e for e in self.events if e.kind == kind]


def _utc(ns: int | None) -> str:
    if ns is None:
        return "?"
    sec, rest = divmod(int(ns), _NS)
    try:
        t = datetime.fromtimestamp(sec, UTC)
    except (OverflowError, OSError, ValueError):
        return f"{ns} ns"
    return f"{t:%Y-%m-%d %H:%M:%S}.{rest // 10_000_000:02d} UTC"


def _as_ns(t: int | float | datetime | None) -> int | None:
    if t is None:
        return None
    if isinstance(t, datetime):
        if t.tzinfo is None:
            raise ValueError(f"time {t} has no time zone; give UTC explicitly")
        return round(t.timestamp() * _NS)
    return int(t)


#: channel ids our writer gives the topics (in CHANNELS order, from 1), for a file of ours
#: whose channel records were lost with its first chunk
_OUR_CHANNEL_IDS = {topic: i for i, topic in enumerate(CHANNELS, start=1)}


class _FileReader:
    """Reads the scans, events and metadata of one file, trusting only what checks out."""

    def __init__(self, path: Path, since: int | None, until: int | None) -> None:
        self.path = path
        self.since, self.until = since, until
        self.blocks: list[bytes] = []
        self.event_data: list[bytes] = []
        self.metadata: dict[str, dict[str, str]] = {}
        self.channels: dict[int, Channel] = {}
        self.damage: dict[int, Damage] = {}
        self.ours = True
        self._messages: list[tuple[int, int, bytes]] = []  # (chunk offset, channel, data)

    # -------------------------------------------------------------- whole file

    def read(self) -> tuple[np.ndarray, RecordingFile, list[Event]]:
        try:
            with open(self.path, "rb") as f:
                data = f.read()
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        info = RecordingFile(self.path, complete=False)
        if not data:
            info.note = "empty file (created, nothing written)"
            return scan_rows.empty(), info, []
        buf = memoryview(data)
        if not data.startswith(MAGIC):
            if MAGIC.startswith(data):
                info.note = f"only {len(data)} bytes (created, nothing written)"
                return scan_rows.empty(), info, []
            if _NAME_RE.match(self.path.name) is None and not _has_intact_chunk(buf):
                raise RecordingError(f"{self.path}: not an MCAP file (no MCAP magic bytes)")
        header = read_header(buf)
        self.ours = header is None or header.library.startswith("loopcal")
        summary, why = read_summary(buf, strict=self.ours)
        if summary is not None and (summary.chunk_indexes or summary.statistics is not None):
            self._read_indexed(buf, summary)
            info.complete = True
        else:
            self._read_stream(buf)
            info.note = (f"no summary ({why}): read record by record up to its last intact "
                         "chunk")  # fmt: skip
            if why not in ("no footer (the file was not closed)", "no summary section"):
                info.damage.append(Damage(len(buf), 0, f"index unusable ({why})"))
        self._check_is_recording()
        rows, events, bad, info.last_scan_chunk = self._decode()
        info.bad_messages = bad
        info.metadata = self.metadata
        info.damage += sorted(self.damage.values(), key=lambda d: d.offset)
        rows = self._window(rows)
        rows, info.duplicates = _unique_scans(rows)
        info.lost = _losses(rows)
        info.scans = len(rows)
        if len(rows):
            info.first_stamp_ns = int(rows["stamp_ns"][0])
            info.last_stamp_ns = int(rows["stamp_ns"][-1])
        return rows, info, events

    def _check_is_recording(self) -> None:
        topics = {c.topic for c in self.channels.values()}
        if TOPIC_SCANS not in topics and "loopcal" not in self.metadata and not self.blocks:
            if not self.ours or (not self.damage and self.channels):
                listed = ", ".join(sorted(topics)) or "none"
                raise RecordingError(
                    f"{self.path}: an MCAP file but not a loopcal recording: it has no "
                    f"{TOPIC_SCANS} channel (its topics: {listed})"
                )
        fmt = self.metadata.get("loopcal", {}).get("format")
        if fmt is not None and fmt != FORMAT_VERSION:
            raise RecordingError(
                f"{self.path}: recording format {fmt}, this loopcal reads format {FORMAT_VERSION}"
            )

    # -------------------------------------------------------------- records

    def _ids(self, *topics: str) -> set[int]:
        ids = {i for i, c in self.channels.items() if c.topic in topics}
        if not ids and self.ours and not self.channels:
            ids = {_OUR_CHANNEL_IDS[t] for t in topics}
        return ids

    def _in_window(self, start: int, end: int) -> bool:
        if self.since is not None and end + BLOCK_SPAN_NS < self.since:
            return False
        return not (self.until is not None and start >= self.until)

    def _take(self, got: ChunkRecords | Damage) -> None:
        if isinstance(got, Damage):
            self.damage.setdefault(got.offset, got)
            return
        for ch in got.channels:
            self.channels.setdefault(ch.id, ch)
        self._messages += [(got.offset, cid, data) for cid, _t, data in got.messages]

    def _read_indexed(self, buf: memoryview, summary: Summary) -> None:
        self.channels = dict(summary.channels)
        for idx in summary.metadata_indexes:
            at = record_at(buf, idx.offset, len(buf))
            if at is None or at[0] != Opcode.METADATA or idx.length != RECORD_HEAD + at[1]:
                self.damage.setdefault(idx.offset, Damage(idx.offset, idx.length,
                                                          "no metadata where the index says"))
                continue
            try:
                rec = parse_record(Opcode.METADATA, buf[idx.offset + RECORD_HEAD :
                                                         idx.offset + idx.length])
            except PARSE_ERRORS:
                self.damage.setdefault(idx.offset, Damage(idx.offset, idx.length,
                                                          "damaged metadata record"))
                continue
            self.metadata[rec.name] = dict(rec.metadata)
        wanted = self._ids(TOPIC_SCANS, TOPIC_EVENTS)
        for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
            offsets = ci.message_index_offsets
            if offsets and wanted.isdisjoint(offsets):
                continue
            if not self._in_window(ci.message_start_time, ci.message_end_time):
                continue
            got = read_chunk(buf, ci.chunk_start_offset, strict=self.ours, wanted=wanted,
                             expected_length=ci.chunk_length)  # fmt: skip
            if isinstance(got, Damage) and got.end_ns is None:
                got = Damage(got.offset, got.length, got.what, ci.message_start_time,
                             ci.message_end_time)  # fmt: skip
            self._take(got)

    def _read_stream(self, buf: memoryview) -> None:
        """Every chunk in file order (the message indexes after a chunk are not trusted to
        say what it holds: a flipped channel id there would hide scans)."""
        for rec in walk(buf, strict=self.ours, wanted=lambda: None):
            if isinstance(rec, ChunkRecords):
                if self._in_window(rec.start_ns, rec.end_ns):
                    self._take(rec)
                else:
                    self._take(ChunkRecords(rec.offset, rec.start_ns, rec.end_ns, rec.channels))
            elif isinstance(rec, Damage):
                self._take(rec)
            elif isinstance(rec, Metadata):
                self.metadata.setdefault(rec.name, dict(rec.metadata))
            elif isinstance(rec, Channel):
                self.channels.setdefault(rec.id, rec)

    def _decode(self) -> tuple[np.ndarray, list[Event], int, int]:
        """Scan rows, events, how many messages did not decode, and the offset of the last
        chunk that gave scans."""
        scans_ids = self._ids(TOPIC_SCANS)
        event_ids = self._ids(TOPIC_EVENTS)
        blocks: list[bytes] = []
        events: list[Event] = []
        bad = 0
        last_chunk = -1
        for offset, cid, data in self._messages:
            if cid in scans_ids:
                blocks.append(data)
                last_chunk = max(last_chunk, offset)
            elif cid in event_ids:
                try:
                    events.append(Event.from_json(json.loads(data)))
                except (ValueError, TypeError, KeyError, AttributeError, RecursionError):
                    bad += 1
        rows, bad_blocks = decode_scan_blocks_checked(blocks)
        bad += bad_blocks
        seen: set[tuple[int, str, str]] = set()
        unique = []
        for e in events:  # a chunk read twice repeats its events
            key = (e.stamp_ns, e.kind, e.message)
            if key not in seen:
                seen.add(key)
                unique.append(e)
        return rows, unique, bad, last_chunk

    def _window(self, rows: np.ndarray) -> np.ndarray:
        if self.since is None and self.until is None:
            return rows
        s = rows["stamp_ns"]
        mask = np.ones(len(rows), dtype=bool)
        if self.since is not None:
            mask &= s >= self.since
        if self.until is not None:
            mask &= s < self.until
        return rows[mask]


def _has_intact_chunk(buf: memoryview) -> bool:
    """Whether a file without MCAP magic still holds a chunk that checks out (a damaged
    start), as opposed to bytes that were never a recording."""
    for rec in walk(buf, strict=False, wanted=lambda: set()):
        if isinstance(rec, ChunkRecords):
            return True
    return False


def _in_order(rows: np.ndarray) -> bool:
    e, c = rows["epoch"], rows["counter64"]
    return bool(np.all((e[1:] > e[:-1]) | ((e[1:] == e[:-1]) & (c[1:] > c[:-1]))))


def _unique_scans(rows: np.ndarray) -> tuple[np.ndarray, int]:
    """Rows in (epoch, counter64) order, each key once (the first kept); and how many
    repeats were dropped. Within a file a key names one scan."""
    if len(rows) < 2 or _in_order(rows):
        return rows, 0
    rows = rows[np.lexsort((rows["counter64"], rows["epoch"]))]
    e, c = rows["epoch"], rows["counter64"]
    keep = np.ones(len(rows), dtype=bool)
    keep[1:] = (e[1:] != e[:-1]) | (c[1:] != c[:-1])
    return rows[keep], int(len(rows) - keep.sum())


def _losses(rows: np.ndarray) -> list[Loss]:
    """Counter gaps between consecutive scans of a file that their ``missed`` counts do not
    explain: within an epoch, ``counter - previous - 1 > missed``; at a new epoch's first
    scan in the file, ``counter > missed``."""
    if len(rows) < 2:
        return []
    e, c, m = rows["epoch"], rows["counter64"], rows["missed"].astype(np.uint64)
    same = e[1:] == e[:-1]
    step = np.where(same, c[1:] - c[:-1] - np.uint64(1), c[1:])
    out = []
    for i in np.flatnonzero(step > m[1:]):
        first = int(c[i]) + 1 if same[i] else int(m[i + 1])
        out.append(Loss(int(e[i + 1]), first, int(step[i] - m[i + 1]),
                        int(rows["stamp_ns"][i]), int(rows["stamp_ns"][i + 1])))  # fmt: skip
    return out


def _identity(rows: np.ndarray) -> list[bytes]:
    """What makes a scan the same scan in two files: epoch, counter, device time, codes."""
    packed = np.zeros(len(rows), dtype=[("e", "<u4"), ("c", "<u8"), ("t", "<u8"),
                                        ("k", "<u2", (4,))])  # fmt: skip
    packed["e"], packed["c"] = rows["epoch"], rows["counter64"]
    packed["t"], packed["k"] = rows["time64_us"], rows["codes"]
    raw = packed.tobytes()
    k = packed.dtype.itemsize
    return [raw[i : i + k] for i in range(0, len(raw), k)]


def _key_range(rows: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    return ((int(rows["epoch"][0]), int(rows["counter64"][0])),
            (int(rows["epoch"][-1]), int(rows["counter64"][-1])))  # fmt: skip


def _read_tail_statistics(path: Path) -> Statistics | None:
    """The statistics record of a closed file, reading only its first and last bytes."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
            size = os.fstat(f.fileno()).st_size
            if size < 8 + FOOTER_BYTES + 8 or not head.startswith(MAGIC):
                return None
            f.seek(size - 8 - FOOTER_BYTES)
            footer = f.read(FOOTER_BYTES + 8)
            (start,) = struct.unpack_from("<Q", footer, RECORD_HEAD)
            if not 8 <= start <= size - 8 - FOOTER_BYTES:
                return None
            f.seek(start)
            tail = f.read()
    except (OSError, struct.error):
        return None
    header = read_header(memoryview(head))
    ours = header is None or header.library.startswith("loopcal")
    return read_statistics(memoryview(tail), strict=ours, base=start)


def message_time_range(path: Path) -> tuple[int, int] | None:
    """(first, last) message log time of a closed file from its statistics record alone
    (footer -> summary offsets -> statistics, the summary checked by its CRC), or None if
    the file has no intact one."""
    stats = _read_tail_statistics(path)
    if stats is None or not stats.message_count:
        return None
    return stats.message_start_time, stats.message_end_time


def read_recordings(
    paths: str | os.PathLike | Iterable[str | os.PathLike],
    *,
    since: int | float | datetime | None = None,
    until: int | float | datetime | None = None,
) -> Recording:
    """Load one or many recording files into numpy arrays.

    paths: files or directories (all recordings in them). Files are put in time order by
    their first scan. since, until: keep scans with ``since <= stamp < until`` (ns since the
    Unix epoch, or aware datetimes); events likewise.

    Whatever the bytes, it returns the scans that are intact, each once, and says in each
    file's :class:`RecordingFile` what could not be read (:attr:`Recording.warnings` has one
    line per damaged or partly read file). A file that was not closed (crash, power loss)
    is read up to its last intact chunk. Nothing that fails a check (a CRC, a length, an
    index offset) is returned. Raises :class:`RecordingError` for a file that is missing or
    unreadable, not MCAP at all, not a loopcal recording, or of another format version,
    and ValueError for an empty time window.
    """
    items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
    files: list[Path] = []
    for item in map(Path, items):
        files += find_recordings(item) if item.is_dir() else [item]
    files = list(dict.fromkeys(files))  # a file named twice is read once
    lo, hi = _as_ns(since), _as_ns(until)
    if lo is not None and hi is not None and hi <= lo:
        raise ValueError(
            f"empty time window: until ({_utc(hi)}) is not after since ({_utc(lo)})"
        )
    parts: list[tuple[np.ndarray, RecordingFile, list[Event]]] = []
    for path in files:
        if not path.exists():
            raise RecordingError(f"{path}: no such file")
        if lo is not None or hi is not None:
            span = message_time_range(path)  # skip whole files outside the window cheaply
            if span is not None and not (
                (lo is None or span[1] + BLOCK_SPAN_NS >= lo) and (hi is None or span[0] < hi)
            ):
                continue
        parts.append(_FileReader(path, lo, hi).read())
    parts.sort(key=lambda x: (x[1].first_stamp_ns is None, x[1].first_stamp_ns or 0, x[1].path))
    kept: list[np.ndarray] = []
    ranges: list[tuple[tuple[int, int], tuple[int, int]]] = []
    events: list[Event] = []
    for rows, info, evs in parts:
        if len(rows):
            lo_k, hi_k = _key_range(rows)
            overlapping = [i for i, (a, b) in enumerate(ranges) if a <= hi_k and lo_k <= b]
            if overlapping:  # the same scan in two files (copies, or a recorder restart)
                seen = {k for i in overlapping for k in _identity(kept[i])}
                dup = np.fromiter((k in seen for k in _identity(rows)), bool, len(rows))
                if dup.any():
                    rows = rows[~dup]
                    info.scans = len(rows)
            if len(rows):
                ranges.append(_key_range(rows))
                kept.append(rows)
        events += evs
    rows = np.concatenate(kept) if kept else scan_rows.empty()
    if lo is not None or hi is not None:
        events = [e for e in events if (lo is None or e.stamp_ns >= lo)
                  and (hi is None or e.stamp_ns < hi)]  # fmt: skip
    events.sort(key=lambda e: e.stamp_ns)
    return Recording(rows, events, [info for _, info, _ in parts])


def last_scan(
    directory: str | os.PathLike, problems: list[str] | None = None
) -> tuple[np.void, dict[str, dict[str, str]]] | None:
    """The newest scan recorded in a directory and its file's metadata, or None.

    For a recorder that starts again: it continues the power-on epoch and counts the scans
    lost while it was down. Files are tried newest first; a damaged one gives its last
    intact scan, an unreadable one is skipped. What was wrong with each file is appended to
    ``problems`` (one line each), for the recorder to report.
    """
    try:
        files = find_recordings(directory)
    except RecordingError as exc:
        if problems is not None:
            problems.append(str(exc))
        return None
    for path in reversed(files):
        try:
            rec = read_recordings([path])
        except RecordingError as exc:
            if problems is not None:
                problems.append(f"{exc}; skipped")
            continue
        if problems is not None:
            problems += rec.warnings
        if len(rec):
            return rec.scans[-1], rec.files[0].metadata
    return None


__all__ = [
    "BLOCK_SPAN_NS",
    "CHANNELS",
    "FORMAT_VERSION",
    "JointStates",
    "Recording",
    "RecordingError",
    "RecordingFile",
    "RecordingWriter",
    "TOPIC_EVENTS",
    "TOPIC_LOG",
    "TOPIC_SCANS",
    "TOPIC_SCENE",
    "TOPIC_STATE",
    "TOPIC_TRANSFORM",
    "decode_scan_blocks",
    "encode_scan_block",
    "find_recordings",
    "joint_states",
    "last_scan",
    "metadata_records",
    "name_time_ns",
    "read_recordings",
    "recording_name",
    "scan_block_msgdef",
]
