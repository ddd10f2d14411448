"""fit -> config: writing new parameter values into the controller config, safely.

Only values change: the file is edited with tomlkit, so its comments and layout survive,
and ``[provenance]`` records where the values came from. Nothing already configured can be
lost or half written (the mechanics are :mod:`loopcal.daemon.config.durable`'s):

1. the config's real file is found through any symlinks (the link stays a link; its target
   is what is replaced, in the target's own directory, with the target's mode);
2. the writer takes the config's advisory lock, so a second calibration writing at the
   same time waits for the first;
3. holding it, the file is read again and must be byte for byte what the calibration
   started from (compare-and-swap: someone, or another calibration, may have written it
   meanwhile; then nothing is written and the calibration must be run again);
4. the current version is copied beside it, ``NAME.YYYYmmddTHHMMSSZ.prev`` (a name no
   other writer has taken), durably;
5. the new version goes to a temporary file in the same directory, is fsynced, renamed over
   the file (atomic), and the directory is fsynced; then the lock is released.

Killed at any point, the config is the old version or the new one, never a mix.

For tests, ``LOOPCAL_KILL_AT`` set to one of :data:`STEPS` makes the process SIGKILL itself
right after that step, and ``LOOPCAL_PAUSE_AT=STEP:SECONDS`` holds it there.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tomlkit

from loopcal.calibration.parameters import NAMES

from ..config import durable
from ..config.controller import ControllerConfig, ControllerConfigError
from ..times import name_stamp

#: the write sequence's steps, in order (the config is new from ``new-renamed`` on)
STEPS = ("locked", "backup-written", "backup-renamed", "new-written", "new-renamed",
         "new-synced")  # fmt: skip


@dataclass(frozen=True)
class Written:
    """Where write_back put things: the config path as given, the file actually replaced
    (its symlink target, or the same path), and the previous version kept beside it."""

    path: Path
    target: Path
    backup: Path

    @property
    def through_link(self) -> bool:
        return self.target != self.path


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


def check_writable(config: ControllerConfig) -> Path:
    """Fail early, before a calibration runs, if its result could not be written: the
    config's real file must exist and its directory take new files. Returns the real file.
    Raises ControllerConfigError."""
    path = config.path
    if path is None:
        raise ControllerConfigError("no controller config file to write to")
    try:
        target = durable.target_of(path)
    except OSError as exc:
        raise ControllerConfigError(f"{path}: {exc.strerror or exc}") from None
    try:
        durable.check_can_replace(target)
    except OSError as exc:
        raise ControllerConfigError(
            f"{path}: cannot be replaced in {target.parent}: {exc.strerror or exc}"
        ) from None
    return target


def write_back(
    config: ControllerConfig, params: np.ndarray, provenance: dict[str, Any], *,
    lock_timeout: float = durable.LOCK_TIMEOUT_S,
) -> Written:  # fmt: skip
    """Write every parameter whose value differs from the config's into it, with
    ``provenance``. Returns where it wrote.

    Raises ControllerConfigError if the file changed since it was read (nothing written:
    run the calibration again), another writer held it too long, or it cannot be written
    (the config is then as it was).
    """
    path = config.path
    if path is None:
        raise ControllerConfigError("no controller config file to write to")
    try:
        target = durable.target_of(path)
        with durable.locked(target, timeout=lock_timeout):
            durable.step("locked")
            raw = target.read_bytes()
            mode = os.stat(target).st_mode & 0o7777
            if hashlib.sha256(raw).hexdigest() != config.sha256:
                raise ControllerConfigError(
                    f"{path}: changed since the calibration read it (another calibration or "
                    "an edit wrote it meanwhile); nothing written: run the calibration again"
                )
            new = {n: float(v) for n, v, old in zip(NAMES, params, config.params, strict=True)
                   if v != old}  # fmt: skip
            text = updated_text(config.text, new, provenance)
            backup = _keep_previous(target, raw, mode)
            durable.replace(target, text.encode("utf-8"), mode=mode, prefix="new-")
    except durable.Busy as exc:
        raise ControllerConfigError(f"{path}: {exc.strerror}; nothing written") from None
    except OSError as exc:
        raise ControllerConfigError(
            f"{path}: cannot write the new values: {exc.strerror or exc} (unchanged)"
        ) from None
    return Written(path, target, backup)


def _keep_previous(target: Path, raw: bytes, mode: int) -> Path:
    """Copy the current version beside the target under a name nobody has taken."""
    stamp = name_stamp()
    n = 1
    while True:
        suffix = stamp if n == 1 else f"{stamp}-{n}"
        backup = target.with_name(f"{target.name}.{suffix}.prev")
        try:
            durable.create_new(backup, raw, mode, prefix="backup-")
            return backup
        except FileExistsError:
            n += 1
