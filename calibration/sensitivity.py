"""How a parameter error moves the plate orientation computed from the sensors (the paper's
Figure 3): the controller reads voltages V, believes parameters ``p + delta e_j`` (so lengths
``S' V + d0'``), and solves forward kinematics; the difference to the true orientation is the
error that parameter causes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .kinematics import (
    check_rotations,
    euler_zyz,
    forward_kinematics,
    inverse_kinematics,
    lengths_to_volts,
    volts_to_lengths,
)
from .parameters import check_vector, index_of


@dataclass(frozen=True)
class OrientationError:
    """euler_deg: (m, 3) change of the Z-Y-Z angles (alpha, beta, gamma), degrees, wrapped to
    (-180, 180]; angle_deg: (m,) angle of the relative rotation, degrees (free of the Euler
    singularity at zero tilt, where alpha and gamma alone are ill-defined)."""

    parameter: str
    delta: float
    euler_deg: np.ndarray
    angle_deg: np.ndarray


def orientation_error(R: np.ndarray, p: np.ndarray, name: str, delta: float = 1.0):
    """Orientation error at true rotations R (m, 3, 3) when parameter ``name`` is believed
    ``delta`` (its unit) off its true value in ``p``."""
    R = check_rotations(R)
    p = check_vector(p)
    V = lengths_to_volts(inverse_kinematics(R, p), p)
    wrong = p.copy()
    wrong[index_of(name)] += delta
    R_hat = forward_kinematics(volts_to_lengths(V, wrong), wrong).rotations
    diff = np.degrees(euler_zyz(R_hat) - euler_zyz(R))
    diff = (diff + 180.0) % 360.0 - 180.0
    rel = np.swapaxes(R, 1, 2) @ R_hat
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return OrientationError(name, float(delta), diff, np.degrees(np.arccos(cos)))
