"""What a recording holds: topics, channels, the schemas of their messages, and the format's
version (the layout of each message is :mod:`~loopcal.daemon.recording.cdr`'s)."""

from __future__ import annotations

import json
from typing import Any

from ..scan_rows import SCAN_FIELDS

#: the format of files as the recorder writes them (raw scans as ScanBlock rows)
FORMAT_VERSION = "1"
#: the format of compacted files (raw scans as ScanColumns, docs/recording.md)
COMPACT_FORMAT = "2"
#: the formats this loopcal reads
READ_FORMATS = (FORMAT_VERSION, COMPACT_FORMAT)


def format_words(fmt: str) -> str:
    """Why a file of recording format ``fmt`` (not one of :data:`READ_FORMATS`) is not
    read: a newer loopcal's (a larger number) wants loopcal upgraded."""
    known = ", ".join(READ_FORMATS)
    # a hostile file's value: shown short and printable, compared as ASCII digits only
    # (int() refuses other digits, and strings of thousands of them)
    shown = fmt if len(fmt) <= 32 and fmt.isprintable() else f"{fmt[:32]!r}..."
    number = fmt.lstrip("0") if fmt.isascii() and fmt.isdigit() else None
    if number and (len(number) > 9 or int(number) > max(int(f) for f in READ_FORMATS)):
        return (
            f"recording format {shown}, written by a newer loopcal: this one reads formats "
            f"{known}; upgrade loopcal to read it"
        )
    return f"recording format {shown}, this loopcal reads formats {known}"


TOPIC_SCANS = "/daq/scans"
TOPIC_EVENTS = "/loopcal/events"
TOPIC_LOG = "/loopcal/log"
TOPIC_STATE = "/joint/state"
TOPIC_TRANSFORM = "/plate/transform"
TOPIC_SCENE = "/plate/scene"

SCAN_BLOCK_SCHEMA = "loopcal_msgs/msg/ScanBlock"
SCAN_COLUMNS_SCHEMA = "loopcal_msgs/msg/ScanColumns"
JOINT_STATE_SCHEMA = "loopcal_msgs/msg/JointState"
FRAME_TRANSFORM_SCHEMA = "foxglove_msgs/msg/FrameTransform"
BASE_FRAME, PLATE_FRAME = "base", "plate"

CDR_LE = b"\x00\x01\x00\x00"  # CDR encapsulation header: little endian, no options
#: a raw block never spans more stamp time than this (readers widen time windows by it)
BLOCK_SPAN_NS = 1_000_000_000
#: a compacted file's block of columns holds at most this much stamp time, all before its
#: log time (a chunk of a compacted file spans at most as much)
COLUMNS_SPAN_NS = 60_000_000_000
NS_PER_S = 1_000_000_000

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


def our_channel_id(topic: str) -> int:
    """The channel id our writer gives ``topic`` (one of :data:`CHANNELS`): they are
    registered in that order, from 1. Readers fall back on it for a file of ours whose
    channel records were lost with its first chunk."""
    return list(CHANNELS).index(topic) + 1


def our_topic(channel_id: int) -> str | None:
    """The topic our writer gives channel ``channel_id`` (:func:`our_channel_id`'s
    inverse), or None for an id it never gives."""
    topics = list(CHANNELS)
    return topics[channel_id - 1] if 1 <= channel_id <= len(topics) else None


def scan_columns_msgdef() -> str:
    """The ROS 2 message definition of ``/daq/scans`` in a compacted file (``ros2msg``
    schema text): the scans packed column by column (:mod:`.columns`)."""
    return (
        "# LDQ-412 scans, raw and lossless, packed column by column (docs/recording.md):\n"
        "# the same scans a ScanBlock holds. Every scan of the recording is in exactly one\n"
        "# block.\n"
        "uint32 count  # scans in the block\n"
        "uint8 codec  # 1: differences, zigzag, byte planes, zstd\n"
        "uint8[] data  # header and compressed planes\n"
    )


def schema_bytes(name: str) -> bytes:
    if name == SCAN_BLOCK_SCHEMA:
        return scan_block_msgdef().encode()
    if name == SCAN_COLUMNS_SCHEMA:
        return scan_columns_msgdef().encode()
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
