"""Per-scan views for people: the plate's pose of every scan (forward kinematics at the
controller config), as ``/joint/state``, ``/plate/transform`` and ``/plate/scene`` messages."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

import numpy as np

from loopcal.calibration.kinematics import (
    base_points,
    euler_zyz,
    forward_kinematics,
    plate_home,
    volts_to_lengths,
)

from .. import scan_rows
from .cdr import FRAME_TRANSFORM_DTYPE, JOINT_STATE_DTYPE, cdr_messages, fill_string_fields
from .schemas import BASE_FRAME, NS_PER_S, PLATE_FRAME

# ---------------------------------------------------------------------------- views


def _stamp(ns: int) -> dict[str, int]:
    sec, nsec = divmod(int(ns), NS_PER_S)
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
            quat[sel] = _quaternions(R)
            euler[sel] = np.degrees(euler_zyz(R))
            rms[sel] = fk.rms_mm[good]
            pose_ok[sel] = True
    a, b, g = euler.T
    swivel = np.degrees(np.angle(np.exp(1j * np.radians(a + g))))
    return JointStates(v, lengths, ok, pose_ok, quat, euler, b, swivel, rms, error)


@dataclass(frozen=True)
class WrittenViews:
    """The per-scan views of one write, as a recording file got them (what the live view
    passes on instead of computing them again): ``/joint/state`` messages (CDR) and their
    log times (ns), one a scan; ``/plate/transform`` messages and theirs, one a scan with a
    pose."""

    state_stamps: np.ndarray
    states: list[bytes]
    transform_stamps: np.ndarray
    transforms: list[bytes]

    def __len__(self) -> int:
        return len(self.states) + len(self.transforms)


def _secs(stamps: np.ndarray, arr: np.ndarray) -> None:
    sec, nsec = np.divmod(stamps.astype(np.int64), NS_PER_S)
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
    fill_string_fields(arr)
    arr["rotation"] = quat.astype(np.float32)
    return cdr_messages(arr)


def scene_message(stamp_ns: int, params: np.ndarray) -> bytes:
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


def _quaternions(R: np.ndarray) -> np.ndarray:
    """(n, 4) unit quaternions x, y, z, w of rotations (n, 3, 3), by scipy's Rotation
    (imported here: scipy.spatial takes 0.3 s to import, and only the recorder needs it)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()
