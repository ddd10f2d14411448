"""The robot controller's calibration config: a TOML file of the 20 parameters.

The controller reads its kinematic and sensor parameters from this file; the recorder reads
it to compute the plate's pose of every scan, and the calibration worker writes new values
back into it. It is read with :mod:`tomllib` and written with :mod:`tomlkit`, which keeps
comments and layout when a value changes. Format::

    # (a header saying what the file is)
    [parameters]
    # Base point A1, x coordinate (A1 lies on the x axis by construction), mm
    A1x = 68.7
    ... all 20, named as in the reference (A1x ... d04), mm or mm/V ...

    [calibration]
    # what a calibration identifies unless told otherwise
    free = "paper7"
    ties = []

    [provenance]   # optional: written by the calibration worker, kept as it is

Any other table or key is an error, and so is a missing or malformed parameter; every
message names the file and the key.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit

from calibration.errors import ParameterError
from calibration.parameters import NAMES, NOMINAL, UNITS, ParameterModel, check_vector

_TABLES = ("parameters", "calibration", "provenance")

#: what each parameter is (the unit follows from calibration.parameters.UNITS)
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
    """A controller config that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class ControllerConfig:
    """A controller config as read.

    path: the file, or None for the built-in reference geometry.
    params: (20,) full parameter vector (read-only).
    free: ``[calibration].free`` or None. ties: ``[calibration].ties``.
    text: the file's exact text ("" for the reference). sha256: of its bytes ("" likewise).
    provenance: the ``[provenance]`` table, or None.
    """

    path: Path | None
    params: np.ndarray
    free: str | None
    ties: tuple[str, ...]
    text: str
    sha256: str
    provenance: dict[str, Any] | None = None

    def model(self) -> ParameterModel:
        """The free/tied/fixed split this config asks for (the paper's seven by default)."""
        return ParameterModel.parse(self.free or "paper7", self.ties)

    def as_metadata(self) -> dict[str, str]:
        """A flat str -> str record for an MCAP metadata record."""
        out = {"path": "" if self.path is None else str(self.path), "sha256": self.sha256}
        out.update({n: repr(float(v)) for n, v in zip(NAMES, self.params, strict=True)})
        out["free"] = self.free or ""
        out["ties"] = ",".join(self.ties)
        if self.provenance is not None:
            out["provenance"] = json.dumps(self.provenance, sort_keys=True, default=str)
        return out


def nominal_config() -> ControllerConfig:
    """The reference geometry, for when no controller config is given."""
    return ControllerConfig(None, NOMINAL, None, (), "", "")


def load_controller_config(path: str | os.PathLike) -> ControllerConfig:
    """Read and check a controller config; raises ControllerConfigError naming the key."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ControllerConfigError(
            f"{p}: cannot read the controller config: {exc.strerror or exc}"
        ) from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ControllerConfigError(f"{p}: not UTF-8 text") from None
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ControllerConfigError(f"{p}: not valid TOML: {exc}") from None
    for key, value in doc.items():
        if key not in _TABLES:
            raise ControllerConfigError(
                f"{p}: unknown table or key {key!r} (a controller config has "
                f"{', '.join(f'[{t}]' for t in _TABLES)})"
            )
        if not isinstance(value, dict):
            raise ControllerConfigError(f"{p}: {key!r} must be a table [{key}]")
    params = _parameters(p, doc.get("parameters"))
    free, ties = _calibration(p, doc.get("calibration", {}))
    cfg = ControllerConfig(
        p, params, free, ties, text, hashlib.sha256(raw).hexdigest(), doc.get("provenance")
    )
    try:
        cfg.model()
    except ParameterError as exc:
        raise ControllerConfigError(f"{p}: [calibration]: {exc}") from None
    return cfg


def _parameters(p: Path, table: Any) -> np.ndarray:
    if table is None:
        raise ControllerConfigError(f"{p}: no [parameters] table")
    for key in table:
        if key not in NAMES:
            close = difflib.get_close_matches(key, NAMES, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise ControllerConfigError(f"{p}: [parameters].{key}: unknown parameter{hint}")
    missing = [n for n in NAMES if n not in table]
    if missing:
        raise ControllerConfigError(f"{p}: [parameters] lacks {', '.join(missing)}")
    values = []
    for name in NAMES:
        v = table[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ControllerConfigError(f"{p}: [parameters].{name} = {v!r} is not a number")
        if not np.isfinite(v):
            raise ControllerConfigError(f"{p}: [parameters].{name} = {v!r} is not finite")
        values.append(float(v))
    try:
        params = check_vector(np.array(values))
    except ParameterError as exc:
        raise ControllerConfigError(f"{p}: [parameters]: {exc}") from None
    params.setflags(write=False)
    return params


def _calibration(p: Path, table: dict) -> tuple[str | None, tuple[str, ...]]:
    for key in table:
        if key not in ("free", "ties"):
            raise ControllerConfigError(f"{p}: [calibration].{key}: unknown key (free, ties)")
    free = table.get("free")
    if free is not None and (not isinstance(free, str) or not free.strip()):
        raise ControllerConfigError(
            f"{p}: [calibration].free = {free!r}: give a preset or names as a string, "
            'e.g. "paper7" or "d03"'
        )
    ties = table.get("ties", [])
    if not isinstance(ties, list) or not all(isinstance(t, str) for t in ties):
        raise ControllerConfigError(
            f'{p}: [calibration].ties = {ties!r}: give a list of strings like ["A4x=-A1x"]'
        )
    return free, tuple(ties)


def render_initial_config(params: np.ndarray | None = None) -> str:
    """The commented TOML text of a controller config at ``params`` (default: reference)."""
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
    cal.add(tomlkit.comment("What `loopcal calibrate` identifies unless --free says otherwise:"))
    cal.add(tomlkit.comment('a preset (paper7, offsets, all, d01..d04) or names, e.g. "d03".'))
    cal.add("free", "paper7")
    cal.add(tomlkit.comment('Ties for a custom free set, e.g. ["A3x=-A2x", "A4x=-A1x"].'))
    cal.add("ties", tomlkit.array())
    doc.add("calibration", cal)
    return tomlkit.dumps(doc)


def write_initial_config(
    path: str | os.PathLike, *, force: bool = False, params: np.ndarray | None = None
) -> Path:
    """Write a new controller config atomically (temporary file, fsync, rename, fsync of the
    directory). Refuses to replace an existing file unless ``force``."""
    p = Path(path)
    if p.exists() and not force:
        raise ControllerConfigError(f"{p}: already exists; use --force to overwrite it")
    if not p.parent.is_dir():
        raise ControllerConfigError(f"{p}: directory {p.parent} does not exist")
    text = render_initial_config(params)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
        fd = os.open(p.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise ControllerConfigError(f"{p}: cannot write: {exc.strerror or exc}") from None
    return p
