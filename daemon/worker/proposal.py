"""A recalibration the daemon proposes: a complete controller config beside the one in force,
that a person applies (or discards) with one command.

The daemon's upkeep (:mod:`loopcal.daemon.live.upkeep`), in ``propose`` mode, writes
``controller.toml.proposed`` beside ``controller.toml`` (the path as configured, beside a
symlink if it is one): the config in force with the changed offsets' new values and a
``[provenance]`` whose ``upkeep`` table says what was found (when the change began, which
sensors, the shifts and their std, the scans and the window they came from, the gates) and
binds the proposal to its base: the SHA-256 of the config it was made from, and a digest of
the proposed values. Written durably (a temporary file renamed over, the directory
synced), under the config directory's write lock.

:func:`read_proposal` refuses, naming why, a proposal that is damaged (not a controller
config, no ``upkeep`` table), made from another version of the config (the config changed
since), or edited by hand (its values or provenance no longer match the digest).
:func:`apply_proposal` checks the gates again on the proposal's own window of the
recordings, then writes through the normal path (:func:`~.writeback.write_back`: the
previous version kept, provenance recorded) and removes the proposal;
:func:`discard_proposal` renames it aside (``.discarded``), so nothing proposed is lost.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from loopcal.calibration.parameters import INDEX

from ..config import durable
from ..config.controller import ControllerConfig, ControllerConfigError, load_controller_config
from ..recording import RecordingError, read_recordings
from ..times import name_stamp, now_text
from .offsets import refit_offsets
from .writeback import Written, updated_text, write_back

SUFFIX = ".proposed"


def proposal_path(config_path: Path) -> Path:
    """Where the proposal for ``config_path`` lives: the same name with ``.proposed``."""
    return config_path.with_name(config_path.name + SUFFIX)


def _digest(values: dict[str, float], upkeep: dict[str, Any]) -> str:
    """What binds a proposal's values to its provenance (a hand edit of either breaks it)."""
    body = {k: v for k, v in upkeep.items() if k != "digest"}
    text = json.dumps({"values": values, "upkeep": body}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def proposal_provenance(
    config: ControllerConfig, values: dict[str, float], std: dict[str, float],
    upkeep: dict[str, Any], cov: np.ndarray | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The ``[provenance]`` of a proposed (or written) config: the values' std merged into
    the config's recorded ones (health weighs every parameter by them), the four offsets'
    covariance ``cov`` (4, 4) mm^2 if given (``offset_cov``: what the offsets held carried
    into the fixed ones, :func:`~loopcal.daemon.worker.offsets.fixed_cov`), and ``upkeep``
    (what the daemon found) with the base config's SHA-256 and the digest."""
    previous = (config.provenance or {}).get("std") or {}
    merged = {**(previous if isinstance(previous, dict) else {}),
              **{n: round(float(s), 6) for n, s in std.items()}}  # fmt: skip
    up = {**upkeep, "base_sha256": config.sha256,
          "values": {n: float(v) for n, v in values.items()}}  # fmt: skip
    up["digest"] = _digest(up["values"], up)
    out = {
        "written_utc": now_text(),
        "method": "ml",
        "identified": list(values),
        "std": merged,
        "previous": {n: float(config.params[INDEX[n]]) for n in values},
        "upkeep": up,
    }
    if cov is not None:
        out["offset_cov"] = [[float(f"{c:.6g}") for c in row] for row in np.asarray(cov)]
    return out


def write_proposal(config: ControllerConfig, values: dict[str, float],
                   std: dict[str, float], upkeep: dict[str, Any],
                   cov: np.ndarray | None = None) -> Path:  # fmt: skip
    """Write the proposal for ``config`` durably (``cov``: :func:`proposal_provenance`);
    returns its path.

    Raises
    ------
    ControllerConfigError
        If the config has no file, or the proposal cannot be written (naming why).
    """
    if config.path is None:
        raise ControllerConfigError("no controller config file to propose beside")
    path = proposal_path(config.path)
    prov = proposal_provenance(config, values, std, upkeep, cov)
    text = updated_text(config.text, values, prov)
    try:
        mode = os.stat(durable.target_of(config.path)).st_mode & 0o7777
        with durable.locked(path):
            durable.replace(path, text.encode("utf-8"), mode=mode, prefix="proposal-")
    except OSError as exc:
        raise ControllerConfigError(f"{path}: cannot write the proposal: "
                                    f"{exc.strerror or exc}") from None  # fmt: skip
    return path


@dataclass(frozen=True)
class Proposal:
    """A proposal read back and checked: its file, the config it makes, what was found."""

    path: Path
    config: ControllerConfig
    values: dict[str, float]
    upkeep: dict[str, Any]

    @property
    def std(self) -> dict[str, float]:
        std = (self.config.provenance or {}).get("std") or {}
        return {n: float(std[n]) for n in self.values if n in std}

    def describe(self) -> str:
        """One line: which offsets, to what, since when."""
        parts = [f"{n} {self.values[n]:.4f} mm ({self.upkeep.get('shift_mm', {}).get(n, 0):+.3f}"
                 f" +- {self.std.get(n, float('nan')):.3f})" for n in self.values]  # fmt: skip
        return (f"{', '.join(parts)}; the change began {self.upkeep.get('change_since_utc', '?')}"
                f", proposed {self.upkeep.get('proposed_utc', '?')}")  # fmt: skip


def read_proposal(config: ControllerConfig) -> Proposal | None:
    """The proposal beside ``config``, checked (module docstring); None if there is none.

    Raises
    ------
    ControllerConfigError
        If it is damaged, made from another version of the config, or edited by hand,
        naming which.
    """
    if config.path is None:
        return None
    path = proposal_path(config.path)
    if not os.path.lexists(path):
        return None
    try:
        proposed = load_controller_config(path)
    except ControllerConfigError as exc:
        raise ControllerConfigError(f"the proposal is damaged ({exc}): nothing applied; "
                                    "discard it (loopcal upkeep discard)") from None
    up = (proposed.provenance or {}).get("upkeep")
    if not isinstance(up, dict) or not isinstance(up.get("values"), dict):
        raise ControllerConfigError(f"{path}: not a proposal of the daemon's (no "
                                    "[provenance.upkeep] with its values): nothing "
                                    "applied")  # fmt: skip
    values = {str(n): v for n, v in up["values"].items()}
    if not values or any(n not in INDEX or not isinstance(v, float) for n, v in values.items()):
        raise ControllerConfigError(f"{path}: its [provenance.upkeep].values are damaged: "
                                    "nothing applied")  # fmt: skip
    if up.get("digest") != _digest(values, up):
        raise ControllerConfigError(f"{path}: edited since the daemon wrote it (its values "
                                    "or provenance no longer match their digest): nothing "
                                    "applied; discard it")  # fmt: skip
    if up.get("base_sha256") != config.sha256:
        raise ControllerConfigError(
            f"{path}: made from another version of {config.path} (it changed since the "
            "proposal): nothing applied; discard it, the daemon proposes again if the change "
            "stands")  # fmt: skip
    for name, v in zip(INDEX, proposed.params, strict=True):
        want = values.get(name, float(config.params[INDEX[name]]))
        if float(v) != want:
            raise ControllerConfigError(
                f"{path}: {name} = {float(v)!r} where the proposal says {want!r}: edited by "
                "hand; nothing applied")  # fmt: skip
    return Proposal(path, proposed, values, up)


def apply_proposal(config: ControllerConfig, proposal: Proposal, directory: Path, *,
                   target_mm: float) -> Written:  # fmt: skip
    """Check the proposal's gates again on its own window of the recordings in
    ``directory``, write it through :func:`~.writeback.write_back`, and remove it.

    Raises
    ------
    ControllerConfigError
        If its window can no longer be read, a fit on it is refused by a gate or disagrees
        with the proposal (beyond 3 standard deviations), or the write fails; nothing is
        written then.
    """
    up = proposal.upkeep
    since, until = up.get("window_since_ns"), up.get("window_until_ns")
    if not isinstance(since, int) or not isinstance(until, int) or until <= since:
        raise ControllerConfigError(f"{proposal.path}: no window of recordings to check it on")
    try:
        rec = read_recordings(directory, since=since, until=until + 1)
    except (RecordingError, ValueError) as exc:
        raise ControllerConfigError(f"the proposal's recordings cannot be read again: {exc}") \
            from None  # fmt: skip
    if not len(rec):
        raise ControllerConfigError(f"the proposal's window of recordings is no longer in "
                                    f"{directory} (deleted by the retention?): nothing "
                                    "applied; calibrate with loopcal session")  # fmt: skip
    names = list(proposal.values)
    fit = refit_offsets(rec.scans, config, names, target_mm=target_mm)
    if not fit.accepted:
        raise ControllerConfigError(f"the gates refuse the proposal now: {fit.refusal()}; "
                                    "nothing applied")  # fmt: skip
    now, std = fit.values(), fit.std()
    for n in names:
        both = float(np.hypot(std[n], proposal.std.get(n, std[n])))
        if abs(now[n] - proposal.values[n]) > 3 * both:
            raise ControllerConfigError(
                f"a fit of the proposal's window now gives {n} = {now[n]:.4f} mm, not "
                f"{proposal.values[n]:.4f} (more than 3 std apart): nothing applied")  # fmt: skip
    params = np.array(config.params, dtype=float)
    for n, v in proposal.values.items():
        params[INDEX[n]] = v
    prov = dict(proposal.config.provenance or {})
    prov["upkeep"] = {**prov.get("upkeep", {}),
                      "applied_utc": now_text()}  # fmt: skip
    written = write_back(config, params, prov)
    discard_proposal(config, keep=False)
    return written


def discard_proposal(config: ControllerConfig, *, keep: bool = True) -> Path | None:
    """Take the proposal away: renamed aside, ``.proposed.<UTC>.discarded`` (``keep``), or
    removed. Returns where it went (None if there was none, or it was removed)."""
    if config.path is None:
        return None
    path = proposal_path(config.path)
    if not os.path.lexists(path):
        return None
    with durable.locked(path):
        if not keep:
            path.unlink(missing_ok=True)
            durable.fsync_dir(path.parent)
            return None
        stamp = name_stamp()
        aside = path.with_name(f"{path.name}.{stamp}.discarded")
        os.replace(path, aside)
        durable.fsync_dir(path.parent)
    return aside
