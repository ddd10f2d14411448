"""Sensor offset drift of the simulated mechanism: a loose LVDT core, or a sensor replaced
without recalibrating.

A drift moves sensor i's true offset by ``delta_i(t)`` mm, so it reads
``V_i = (d_i - d0_i - delta_i(t)) / S_i``: the lengths are what they were, the sensor reads
them differently. Two shapes, both in device seconds since the module started:

- a step of ``mm`` at ``at`` (held, or for ``duration`` seconds);
- a creep of ``mm_per_min`` from ``at`` (growing for ever, or for ``duration`` seconds and
  then held).

Drifts are functions of time, not state switched by the fault loop, so the same schedule
gives the same scans in the emulator and offline (:mod:`loopcal.simulator.offline`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OffsetDrift:
    """One drift of sensor ``channel``'s offset: a step or a creep, from ``at`` on.

    Attributes
    ----------
    kind : str
        ``"step"``: the offset moves by ``amount`` mm at ``at``; ``"creep"``: it moves by
        ``amount`` mm per minute from ``at`` on.
    channel : int
        The sensor, 1..4.
    at : float
        When the drift starts, s of source time (since the module's first power-on).
    amount : float
        mm (a step) or mm per minute (a creep); either sign.
    duration : float or None, default None
        How long it lasts, s: a step ends (the offset goes back), a creep stops growing
        and is held. None: for ever.

    Raises
    ------
    ValueError
        If ``kind`` is not step or creep, ``channel`` not 1..4, ``at`` negative or not
        finite, ``amount`` not finite, or ``duration`` not positive.

    Notes
    -----
    A positive shift of sensor i's offset makes it read ``V_i = (d_i - d0_i - shift) / S_i``:
    a length ``d`` reads as ``d - shift`` with the unchanged ``d0`` and ``S``.
    """

    kind: str
    channel: int
    at: float
    amount: float
    duration: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("step", "creep"):
            raise ValueError(f"drift kind must be step or creep, got {self.kind!r}")
        if self.channel not in (1, 2, 3, 4):
            raise ValueError(f"drift channel must be 1..4, got {self.channel!r}")
        if not (np.isfinite(self.at) and self.at >= 0 and np.isfinite(self.amount)):
            raise ValueError("drift time must be >= 0 and its amount finite")
        if self.duration is not None and not self.duration > 0:
            raise ValueError("drift duration must be positive")

    def shift_mm(self, t: np.ndarray) -> np.ndarray:
        """The offset change this drift makes at times ``t``.

        Parameters
        ----------
        t : array_like of float, any shape
            Source times, s since the module's first power-on.

        Returns
        -------
        ndarray of float, same shape as ``t``
            The change of the sensor's offset, mm (0 before ``at``).
        """
        t = np.asarray(t, dtype=float)
        if self.kind == "step":
            on = t >= self.at
            if self.duration is not None:
                on &= t < self.at + self.duration
            return np.where(on, self.amount, 0.0)
        end = np.inf if self.duration is None else self.at + self.duration
        minutes = (np.clip(t, self.at, end) - self.at) / 60.0
        return self.amount * minutes


def offset_shift(drifts: tuple[OffsetDrift, ...] | list[OffsetDrift], t: np.ndarray) -> np.ndarray:
    """Each sensor's offset change, summed over the drifts.

    Parameters
    ----------
    drifts : sequence of OffsetDrift
        The drifts (any channels; several on one channel add up).
    t : array_like of float, shape (..., 4)
        Source times, s: column i holds channel i+1's instants.

    Returns
    -------
    ndarray of float, shape (..., 4)
        Column i: the sum of channel i+1's drifts at column i's times, mm.
    """
    t = np.asarray(t, dtype=float)
    out = np.zeros(t.shape)
    for d in drifts:
        out[..., d.channel - 1] += d.shift_mm(t[..., d.channel - 1])
    return out
