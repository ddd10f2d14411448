"""fit -> config: writing new parameter values into the controller config, safely.

Only values change: the file is edited with tomlkit, so its comments and layout survive,
and ``[provenance]`` records where the values came from. Nothing already configured can be
lost or half written:

1. the file is read again and must be byte for byte what the calibration started from
   (someone may have edited it meanwhile);
2. the current version is copied beside it, ``NAME.YYYYmmddTHHMMSSZ.prev``, durably
   (temporary file, fsync, rename, fsync of the directory);
3. the new version goes to a temporary file in the same directory, is fsynced, renamed over
   the config (atomic), and the directory is fsynced.

Killed at any point, the config is the old version or the new one, never a mix.

For tests, ``LOOPCAL_KILL_AT`` set to one of :data:`STEPS` makes the process SIGKILL itself
right after that step (fault injection, like the emulator's).
"""

from __future__ import annotations

import hashlib
import os
import signal
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit

from calibration.parameters import NAMES

from .controller_config import ControllerConfig, ControllerConfigError

STEPS = (
    "backup-written",
    "backup-synced",
    "backup-renamed",
    "new-written",
    "new-synced",
    "renamed",
    "dir-synced",
)


def _step(name: str) -> None:
    if os.environ.get("LOOPCAL_KILL_AT") == name:
        os.kill(os.getpid(), signal.SIGKILL)


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_durably(path: Path, data: bytes, mode: int, *, tmp_step: str, synced_step: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, mode)
        try:
            os.fchmod(fd, mode)  # the old file's mode, whatever the umask
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            _step(tmp_step)
            os.fsync(fd)
        finally:
            os.close(fd)
        _step(synced_step)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def updated_text(text: str, new: dict[str, float], provenance: dict[str, Any]) -> str:
    """The config text with new parameter values and a new ``[provenance]`` table; every
    comment and all other layout kept."""
    doc = tomlkit.parse(text)
    table = doc["parameters"]
    for name, value in new.items():
        if name not in NAMES:
            raise ValueError(f"unknown parameter {name!r}")
        table[name] = float(value)
    prov = tomlkit.table()
    prov.add(tomlkit.comment("Written by `loopcal calibrate --write`; the values above came from"))
    prov.add(tomlkit.comment("these recordings. The previous file is kept beside this one."))
    for key, value in provenance.items():
        prov.add(key, value)
    if "provenance" in doc:
        del doc["provenance"]
    doc.add(tomlkit.nl())
    doc.add("provenance", prov)
    return tomlkit.dumps(doc)


def write_back(
    config: ControllerConfig, params: np.ndarray, provenance: dict[str, Any]
) -> tuple[Path, Path]:
    """Write every parameter whose value differs from the config's into it, with
    ``provenance``. Returns (config path, path of the previous version kept beside it).

    Raises ControllerConfigError if the file changed since it was read, or cannot be written
    (the config is then as it was).
    """
    path = config.path
    if path is None:
        raise ControllerConfigError("no controller config file to write to")
    try:
        raw = path.read_bytes()
        mode = os.stat(path).st_mode & 0o777
    except OSError as exc:
        raise ControllerConfigError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if hashlib.sha256(raw).hexdigest() != config.sha256:
        raise ControllerConfigError(
            f"{path}: changed since the calibration read it; run the calibration again"
        )
    new = {n: float(v) for n, v, old in zip(NAMES, params, config.params, strict=True) if v != old}
    text = updated_text(config.text, new, provenance)
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    backup = path.with_name(f"{path.name}.{stamp}.prev")
    n = 1
    while backup.exists():
        n += 1
        backup = path.with_name(f"{path.name}.{stamp}-{n}.prev")
    try:
        _write_durably(backup, raw, mode, tmp_step="backup-written", synced_step="backup-synced")
        _step("backup-renamed")
        _fsync_dir(path.parent)
        _write_durably(
            path, text.encode("utf-8"), mode, tmp_step="new-written", synced_step="new-synced"
        )
        _step("renamed")
        _fsync_dir(path.parent)
        _step("dir-synced")
    except OSError as exc:
        raise ControllerConfigError(
            f"{path}: cannot write the new values: {exc.strerror or exc} (unchanged)"
        ) from None
    return path, backup
