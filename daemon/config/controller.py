"""The robot controller's calibration config: a TOML file of the 20 parameters.

The controller reads its kinematic and sensor parameters from this file; the recorder reads
it to compute the plate's pose of every scan, and the calibration worker writes new values
back into it. It is read with :mod:`tomllib` and written with :mod:`tomlkit`, which keeps
comments and layout when a value changes. Format::

    # (a header saying what the file is, the units and the frame)
    [parameters]
    # Base point A1, x coordinate (A1 lies on the x axis by construction), mm
    A1x = 68.7
    ... all 20, named as in loopcal.calibration.parameters.NAMES (A1x ... d04), mm or mm/V ...

    [calibration]
    # what a calibration identifies unless told otherwise
    free = "paper7"
    ties = []

    [provenance]   # optional: written by the calibration worker, kept as it is

Values are TOML floats or integers; lengths in mm, gains in mm/V. Any other table or key is
an error, and so is a missing or malformed parameter; every message names the file and the
key.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit

from loopcal.calibration.errors import ParameterError
from loopcal.calibration.kinematics import check_geometry
from loopcal.calibration.parameters import (
    DEFAULT_FREE,
    INDEX,
    NAMES,
    NOMINAL,
    PRESETS,
    UNITS,
    ParameterModel,
    check_vector,
)

from . import durable

#: the tables a controller config may have, in the order they are written
TABLES: tuple[str, ...] = ("parameters", "calibration", "provenance")
#: the keys of ``[calibration]``
CALIBRATION_KEYS: tuple[str, ...] = ("free", "ties")
#: ``[calibration].free`` when the file does not say

#: what each parameter is (the unit follows from loopcal.calibration.parameters.UNITS)
DESCRIPTIONS: dict[str, str] = {
    "A1x": "Base point A1, x coordinate (A1 lies on the x axis by construction)",
    "A2x": "Base point A2, x coordinate (A2 lies in the xy-plane by construction)",
    "A2y": "Base point A2, y coordinate",
    "A3x": "Base point A3, x coordinate",
    "A3y": "Base point A3, y coordinate",
    "A3z": "Base point A3, z coordinate",
    "A4x": "Base point A4, x coordinate",
    "A4y": "Base point A4, y coordinate",
    "A4z": "Base point A4, z coordinate",
    "k1": "Plate: distance from the centre of rotation O to B1 (actuators 1 and 2 end at B1)",
    "k2": "Plate: distance from O to B2 (actuators 3 and 4 end at B2)",
    "k3": "Plate: distance from B1 to B2",
    **{f"S{i}": f"LVDT {i}: gain, length change per volt (d = S V + d0), from the bench"
       for i in range(1, 5)},
    **{f"d0{i}": f"LVDT {i}: offset, the actuator length at 0 V (lost when the LVDT is refitted)"
       for i in range(1, 5)},
}  # fmt: skip

_HEADER = """\
loopcal controller config: the shoulder joint's kinematic and sensor parameters.

Lengths in mm, gains in mm/V. Frame: origin at the plate's centre of rotation O, x from O
towards A1, A2 in the xy-plane, z out of the base towards the plate. Actuators 1 and 2 run
from A1 and A2 to the plate point B1, actuators 3 and 4 from A3 and A4 to B2. Each LVDT
reads d = S V + d0. `loopcal calibrate --write` updates the values it identifies and
records how in [provenance]; comments and layout are kept."""


class ControllerConfigError(ValueError):
    """A controller config that cannot be read, used or written; the message names the file
    and, where there is one, the key."""


@dataclass(frozen=True)
class ControllerConfig:
    """A controller config as read.

    path: the file, or None for the built-in reference geometry.
    params: (20,) full parameter vector in the order of ``NAMES``, mm and mm/V (read-only).
    free: ``[calibration].free`` as written, or None if absent.
    ties: ``[calibration].ties`` as written (empty if absent).
    text: the file's exact text ("" for the reference geometry).
    sha256: hex SHA-256 of the file's bytes ("" for the reference geometry).
    provenance: the ``[provenance]`` table as tomllib read it, or None if absent.

    Two configs compare equal when path, free, ties, text and sha256 do; the values follow
    from the text.
    """

    path: Path | None
    params: np.ndarray = field(compare=False)
    free: str | None
    ties: tuple[str, ...]
    text: str
    sha256: str
    provenance: dict[str, Any] | None = field(default=None, compare=False)

    def model(self) -> ParameterModel:
        """The free/tied/fixed split the config asks for: ``ParameterModel.parse(free or
        "paper7", ties)``. A loaded config is known to give one."""
        return ParameterModel.parse(self.free or DEFAULT_FREE, self.ties)

    def as_metadata(self) -> dict[str, str]:
        """A flat str -> str record for an MCAP metadata record: ``path`` ("" for the
        reference geometry), ``sha256``, each parameter as ``repr(float)`` (exact: ``float()``
        reads it back bit for bit), ``free`` ("" if absent), ``ties`` joined by "," and, if
        present, ``provenance`` as compact JSON (dates and times as their ``str``)."""
        out = {"path": "" if self.path is None else str(self.path), "sha256": self.sha256}
        out.update({n: repr(float(v)) for n, v in zip(NAMES, self.params, strict=True)})
        out["free"] = self.free or ""
        out["ties"] = ",".join(self.ties)
        if self.provenance is not None:
            out["provenance"] = json.dumps(self.provenance, separators=(",", ":"), default=str)
        return out


def params_from_metadata(record: dict[str, str] | None) -> tuple[np.ndarray | None, str]:
    """The 20-vector a recording's ``controller_config`` metadata record gives (what
    :meth:`ControllerConfig.as_metadata` wrote: each parameter as ``repr(float)``, read back
    bit for bit), or None and why not (no record, a parameter missing or not a number, a
    geometry no mechanism has)."""
    if not record:
        return None, "the file has no controller_config metadata record"
    missing = [n for n in NAMES if n not in record]
    if missing:
        return None, f"its controller_config record lacks {', '.join(missing)}"
    values = []
    for name in NAMES:
        try:
            values.append(float(record[name]))
        except ValueError:
            return None, f"its controller_config record has {name} = {record[name]!r}"
    try:
        params = check_geometry(np.array(values))
    except ParameterError as exc:
        return None, f"its controller_config record describes no mechanism: {exc}"
    return params, ""


def nominal_config() -> ControllerConfig:
    """The reference geometry (``loopcal.calibration.parameters.NOMINAL``), for when no controller
    config is given; path None, free None (so the model is paper7), no ties."""
    return ControllerConfig(None, NOMINAL, None, (), "", "")


def load_controller_config(path: str | os.PathLike) -> ControllerConfig:
    """Read and check a controller config.

    Raises ControllerConfigError, naming the file and the key, if the file is missing,
    unreadable, not UTF-8 or not TOML; if ``[parameters]`` lacks a parameter, has an unknown
    one, or a value that is not a finite number or fails ``check_vector``; if there is a table
    or key other than those of the format; or if ``[calibration]`` does not give a valid
    free/tied split.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise ControllerConfigError(
            f"{p}: no such file (write one with `loopcal init-config {p}`)"
        ) from None
    except OSError as exc:
        raise ControllerConfigError(
            f"{p}: cannot read the controller config: {exc.strerror or exc}"
        ) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ControllerConfigError(f"{p}: not UTF-8 text (byte {exc.start})") from None
    if text.startswith("\ufeff"):
        raise ControllerConfigError(f"{p}: starts with a byte order mark; save it without one")
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ControllerConfigError(f"{p}: not valid TOML: {exc}") from None
    unknown = [key for key in doc if key not in TABLES]
    if unknown:
        raise ControllerConfigError(
            f"{p}: unknown table or key {', '.join(map(repr, unknown))} (a controller config "
            f"has {', '.join(f'[{t}]' for t in TABLES)})"
        )
    for key, value in doc.items():
        if not isinstance(value, dict):
            raise ControllerConfigError(f"{p}: {key} = {value!r} must be a table [{key}]")
    params = _parameters(p, doc.get("parameters"))
    free, ties = _calibration(p, doc.get("calibration", {}))
    return ControllerConfig(
        p, params, free, ties, text, hashlib.sha256(raw).hexdigest(), doc.get("provenance")
    )


def _parameters(p: Path, table: dict[str, Any] | None) -> np.ndarray:
    if table is None:
        raise ControllerConfigError(f"{p}: no [parameters] table (it holds all 20 parameters)")
    unknown = []
    for key in table:
        if key not in NAMES:
            close = difflib.get_close_matches(key, NAMES, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            unknown.append(f"[parameters].{key}: unknown parameter{hint}")
    if unknown:
        raise ControllerConfigError(f"{p}: {'; '.join(unknown)}")
    missing = [n for n in NAMES if n not in table]
    if missing:
        raise ControllerConfigError(f"{p}: [parameters] lacks {', '.join(missing)}")
    values = []
    for name in NAMES:
        v = table[name]
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise ControllerConfigError(f"{p}: [parameters].{name} = {v!r} is not a number")
        try:
            f = float(v)
        except OverflowError:  # TOML integers beyond a double
            f = float("inf")
        if not np.isfinite(f):
            raise ControllerConfigError(f"{p}: [parameters].{name} = {v!r} is not finite")
        values.append(f)
    try:
        params = check_geometry(np.array(values))
    except ParameterError as exc:
        raise ControllerConfigError(f"{p}: [parameters]: {exc}") from None
    params.setflags(write=False)
    return params


def _calibration(p: Path, table: dict[str, Any]) -> tuple[str | None, tuple[str, ...]]:
    for key in table:
        if key not in CALIBRATION_KEYS:
            raise ControllerConfigError(
                f"{p}: [calibration].{key}: unknown key (it has {', '.join(CALIBRATION_KEYS)})"
            )
    free = table.get("free")
    if free is not None:
        if not isinstance(free, str) or not free.strip():
            raise ControllerConfigError(
                f"{p}: [calibration].free = {free!r}: give a preset or names as a string, "
                'e.g. "paper7" or "d01,d02,A1x"'
            )
        try:
            ParameterModel.parse(free)
        except ParameterError as exc:
            raise ControllerConfigError(f"{p}: [calibration].free = {free!r}: {exc}") from None
    ties = table.get("ties", [])
    if not isinstance(ties, list) or not all(isinstance(t, str) for t in ties):
        raise ControllerConfigError(
            f'{p}: [calibration].ties = {ties!r}: give a list of strings like ["A4x=-A1x"]'
        )
    effective = (free or DEFAULT_FREE).strip()
    if ties and effective in PRESETS and effective not in INDEX:
        # with ties, ParameterModel.parse reads free as names, and this name is a preset's
        raise ControllerConfigError(
            f"{p}: [calibration].ties = {ties!r}: the preset {effective!r} brings its own ties; "
            "give ties only with a list of names in [calibration].free"
        )
    try:
        ParameterModel.parse(effective, ties)
    except ParameterError as exc:
        raise ControllerConfigError(f"{p}: [calibration].ties = {ties!r}: {exc}") from None
    return free, tuple(ties)


def render_initial_config(params: np.ndarray | None = None) -> str:
    """The commented TOML text of a controller config at ``params`` ((20,), mm and mm/V;
    default the reference geometry), with ``free = "paper7"`` and no ties.

    Floats are written in their shortest exact form, so the text loads back bit for bit.
    Raises ParameterError if ``params`` fails ``check_vector``.
    """
    p = check_vector(NOMINAL if params is None else params)
    doc = tomlkit.document()
    for line in _HEADER.splitlines():
        doc.add(tomlkit.comment(line) if line else tomlkit.nl())
    doc.add(tomlkit.nl())
    table = tomlkit.table()
    for name, value in zip(NAMES, p, strict=True):
        table.add(tomlkit.comment(f"{DESCRIPTIONS[name]}, {UNITS[name]}"))
        table.add(name, float(value))
    doc.add("parameters", table)
    cal = tomlkit.table()
    cal.add(tomlkit.comment("Parameters a calibration identifies unless told otherwise (--free):"))
    cal.add(tomlkit.comment('a preset (paper7, offsets, all, d01..d04) or names, e.g. "d01,d03"'))
    cal.add("free", DEFAULT_FREE)
    cal.add(tomlkit.comment('Ties for a custom free set, e.g. ["A3x=-A2x", "A4x=-A1x"]'))
    cal.add(tomlkit.comment("(presets bring their own)"))
    cal.add("ties", tomlkit.array())
    doc.add("calibration", cal)
    return tomlkit.dumps(doc)


def write_initial_config(
    path: str | os.PathLike, *, force: bool = False, params: np.ndarray | None = None
) -> Path:
    """Write a new controller config at ``params`` (default the reference geometry) to
    ``path``; returns the file written (``path``'s symlink target when it is a link).

    Atomic (:func:`loopcal.daemon.config.durable.replace`: a temporary file in the same directory,
    fsynced and renamed over, then the directory fsynced), under the config's write lock. Refuses to
    replace an existing file unless ``force`` (a replaced file's permission bits are kept).
    A symlink stays a link: its target is written. Creates no directories. Raises
    ControllerConfigError for all of these.
    """
    p = Path(path)
    try:
        exists = os.path.lexists(p)
        target = durable.target_of(p)
        parent_is_dir = target.parent.is_dir()
        parent_exists = os.path.lexists(target.parent)
    except OSError as exc:
        raise ControllerConfigError(f"{p}: cannot write: {exc.strerror or exc}") from None
    if exists and not force:
        raise ControllerConfigError(f"{p}: already exists; use --force to overwrite it")
    if target.exists() and not target.is_file():
        raise ControllerConfigError(f"{p}: cannot write: {target} is not a regular file")
    if not parent_is_dir:
        what = "is not a directory" if parent_exists else "does not exist"
        raise ControllerConfigError(f"{p}: directory {target.parent} {what}")
    data = render_initial_config(params).encode("utf-8")
    try:
        with durable.locked(target):
            durable.replace(target, data)
    except OSError as exc:
        raise ControllerConfigError(f"{p}: cannot write: {exc.strerror or exc}") from None
    return target
