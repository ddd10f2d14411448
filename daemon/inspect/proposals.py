"""What the daemon's upkeep would propose, from archived recordings (``loopcal check``,
``loopcal fleet check``), and the proposal pending beside a controller config.

:class:`ReportedProposals` is the daemon's upkeep (:class:`~loopcal.daemon.live.upkeep.Upkeep`,
the same code) in report mode, run in the caller's thread: it is fed the scans ``check``
reads, in the same chunks and order (one file at a time), writes nothing, and collects each
recalibration the daemon would have proposed from the robot's own motion: which offsets,
the values and their std, the shifts, when the change began and the window of scans the
values were fitted on. The reference is the controller config alone (a proposal pending
beside it is not taken as the daemon takes it, so a change already proposed is found
again; :func:`pending_proposal` tells it apart).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..config.controller import ControllerConfig, ControllerConfigError
from ..live.upkeep import Upkeep
from ..recorder.settings import DEFAULTS, SETTINGS
from ..times import time_json
from ..worker.proposal import proposal_path, read_proposal

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class UpkeepSettings:
    """The upkeep's settings for an offline run (defaults: the daemon's own).

    Parameters
    ----------
    target_mm : float
        The standard deviation a proposed offset must reach, mm (``[upkeep].target_mm``).
    threshold_mm : float
        The smallest shift of an offset that counts, mm (``[upkeep].threshold_mm``).
    min_interval_s : float
        The least time between two proposals naming the same offset, s
        (``[upkeep].min_interval``).
    """

    target_mm: float = DEFAULTS["upkeep_target_mm"]
    threshold_mm: float = DEFAULTS["upkeep_threshold_mm"]
    min_interval_s: float = DEFAULTS["upkeep_min_interval_s"]

    def checked(self) -> UpkeepSettings:
        """Itself, each value within the daemon's bounds.

        Raises
        ------
        ValueError
            Naming the command-line option (``--upkeep-target-mm``) and its bounds.
        """
        for name in ("target_mm", "threshold_mm"):
            spec = SETTINGS[f"upkeep_{name}"]
            value = getattr(self, name)
            assert spec.lo is not None
            if not (math.isfinite(value) and spec.lo <= value <= spec.hi):
                option = "--upkeep-" + name.replace("_", "-")
                raise ValueError(f"{option} {value:g}: give a length in {spec.lo:g}..{spec.hi:g} "
                                 "mm")  # fmt: skip
        return self


class ReportedProposals:
    """The upkeep in report mode over archived scans (module docstring).

    Parameters
    ----------
    config : ControllerConfig
        The controller config the recordings are checked against.
    settings : UpkeepSettings
        Its target, threshold and minimum interval.
    """

    def __init__(self, config: ControllerConfig, settings: UpkeepSettings) -> None:
        self._upkeep = Upkeep(config, self._emit, mode="report", target_mm=settings.target_mm,
                              threshold_mm=settings.threshold_mm,
                              min_interval_s=settings.min_interval_s, threaded=False)  # fmt: skip
        #: why the upkeep stopped (an exception in a fit: it fails alone, as in the daemon)
        self.failed: str | None = None

    @staticmethod
    def _emit(kind: str, level: object, message: str, **details: Any) -> None:
        """The upkeep's events: nothing to do (its proposals are in its state)."""

    def feed(self, rows: np.ndarray) -> None:
        """Scans (SCAN_DTYPE rows, oldest first), as ``check`` reads them; after a
        failure (:attr:`failed`), ignored."""
        if self.failed is not None or not len(rows):
            return
        try:
            self._upkeep.feed(rows)
        except Exception as exc:  # noqa: BLE001 - the loop-closure check goes on without it
            log.exception("upkeep failed on the scans from %s", time_json(int(rows["stamp_ns"][0])))
            self.failed = (f"upkeep stopped on the scans from "
                           f"{time_json(int(rows['stamp_ns'][0]))}: {type(exc).__name__}: {exc}; "
                           "proposals after that are not reported")  # fmt: skip

    def found(self, first_ns: int | None) -> list[dict[str, Any]]:
        """Each proposal, for ``--json``: ``names``, ``since_utc`` (when the change began),
        ``since_offset_s`` (seconds after ``first_ns``, the recordings' first scan),
        ``values``, ``std`` (what the offsets held carry in counted), ``scans_std`` (the
        scans' own) and ``shift_mm`` (per name, mm), ``window_since_utc`` and
        ``window_until_utc`` (the scans fitted), ``scans``, ``gates`` (each passed)."""
        out = []
        for p in self._upkeep.state.reported:
            out.append({
                "names": list(p["names"]),
                "since_utc": time_json(p["since_ns"]),
                "since_offset_s": (None if first_ns is None
                                   else round((p["since_ns"] - first_ns) / 1e9, 3)),
                "values": dict(p["values"]), "std": dict(p["std"]),
                "scans_std": dict(p["scans_std"]), "shift_mm": dict(p["shift_mm"]),
                "window_since_utc": time_json(p["window_since_ns"]),
                "window_until_utc": time_json(p["window_until_ns"]),
                "scans": p["scans"], "gates": dict(p["gates"]),
            })  # fmt: skip
        return out


def pending_proposal(config: ControllerConfig) -> dict[str, Any] | None:
    """The proposal beside ``config``, for ``--json``; None if there is none.

    Returns
    -------
    dict or None
        ``path``, ``since_utc`` (when the daemon proposed it), ``change_since_utc``,
        ``values`` and ``std`` (mm), ``error`` None; or, for a proposal that cannot be
        taken (damaged, edited, made from another version of the config), ``path`` and
        ``error`` naming why, the rest None.
    """
    if config.path is None:
        return None
    try:
        p = read_proposal(config)
    except ControllerConfigError as exc:
        return {"path": str(proposal_path(config.path)), "since_utc": None,
                "change_since_utc": None, "values": None, "std": None,
                "error": str(exc)}  # fmt: skip
    if p is None:
        return None
    since = p.upkeep.get("proposed_ns")
    change = p.upkeep.get("change_since_ns")
    return {
        "path": str(p.path),
        "since_utc": time_json(since) if isinstance(since, int) else p.upkeep.get("proposed_utc"),
        "change_since_utc": time_json(change) if isinstance(change, int) else None,
        "values": dict(p.values), "std": p.std, "error": None,
    }  # fmt: skip


def proposal_words(p: dict[str, Any]) -> str:
    """A proposal's offsets in words: ``d03 = 99.0765 mm (+0.808 +- 0.011)``."""
    return ", ".join(f"{n} = {p['values'][n]:.4f} mm ({p['shift_mm'][n]:+.3f} +- "
                     f"{p['std'][n]:.3f})" for n in p["names"])  # fmt: skip


def proposal_column(proposals: list[dict[str, Any]]) -> str:
    """``fleet check``'s ``proposals`` column: each offset and its shift (``d03 +0.80``),
    an offset after another of the same proposal after ``, ``, proposals after ``; ``;
    ``-`` for none."""
    if not proposals:
        return "-"
    return "; ".join(", ".join(f"{n} {p['shift_mm'][n]:+.2f}" for n in p["names"])
                     for p in proposals)  # fmt: skip
