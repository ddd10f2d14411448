"""LVDT conversion: ADC code -> volts (datasheet mid-code) -> displacement in mm.

Each conditioner is linear: ``d = S * V + d0`` with gain S in mm/V and offset d0 in mm,
V = ``ldq412.code_to_volts(code)``. Everything is vectorised over numpy arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import ldq412


@dataclass(frozen=True, slots=True)
class LvdtCalibration:
    """One channel's conditioner: gain (mm/V) and offset (mm)."""

    gain_mm_per_v: float
    offset_mm: float = 0.0

    def volts_to_mm(self, volts: np.ndarray | float) -> np.ndarray:
        """d = S * V + d0, mm (any shape)."""
        return self.gain_mm_per_v * np.asarray(volts, dtype=float) + self.offset_mm

    def codes_to_mm(self, codes: np.ndarray | int) -> np.ndarray:
        """ADC codes (any shape) -> mm, via the mid-code reconstruction."""
        return self.volts_to_mm(ldq412.code_to_volts(codes))


def codes_to_volts(codes: np.ndarray | Sequence[int] | int) -> np.ndarray:
    """Mid-code reconstruction ``V = (code + 0.5) * 20 / 4096 - 10``, V (any shape)."""
    return ldq412.code_to_volts(np.asarray(codes))


def volts_to_mm(volts: np.ndarray, cals: Sequence[LvdtCalibration]) -> np.ndarray:
    """Per-channel d = S_i * V_i + d0_i.

    volts: shape (..., n) with n = len(cals), V. Returns mm, same shape.
    """
    v = np.asarray(volts, dtype=float)
    if v.shape[-1:] != (len(cals),):
        raise ValueError(f"last axis of volts is {v.shape[-1:]}, expected ({len(cals)},)")
    gain = np.array([c.gain_mm_per_v for c in cals])
    offset = np.array([c.offset_mm for c in cals])
    return v * gain + offset


def codes_to_mm(
    codes: np.ndarray | Sequence[Sequence[int]],
    cals: Sequence[LvdtCalibration],
    *,
    rail_to_nan: bool = False,
) -> np.ndarray:
    """Per-channel codes (shape (..., n), n = len(cals)) -> displacements, mm.

    rail_to_nan: put NaN where a code is at the rail (0 or 4095), whose reading the
    datasheet calls untrustworthy.
    """
    c = np.asarray(codes)
    mm = volts_to_mm(ldq412.code_to_volts(c), cals)
    if rail_to_nan:
        mm = np.where(ldq412.at_rail(c), np.nan, mm)
    return mm


def code_resolution_mm(cal: LvdtCalibration) -> float:
    """One LSB in mm: |S| * 20 V / 4096."""
    return abs(cal.gain_mm_per_v) * ldq412.V_SPAN / (ldq412.CODE_MAX + 1)
