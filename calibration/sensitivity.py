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
    """The orientation error one parameter error causes (result of
    :func:`orientation_error`).

    Attributes
    ----------
    parameter : str
        The parameter believed wrong.
    delta : float
        By how much, in its unit (mm or mm/V).
    euler_deg : ndarray, shape (m, 3)
        Change of the Z-Y-Z angles (alpha, beta, gamma), degrees, wrapped to [-180, 180).
    angle_deg : ndarray, shape (m,)
        Angle of the relative rotation, degrees (free of the Euler singularity at zero
        tilt, where alpha and gamma alone are ill-defined).
    """

    parameter: str
    delta: float
    euler_deg: np.ndarray
    angle_deg: np.ndarray


def orientation_error(R: np.ndarray, p: np.ndarray, name: str, delta: float = 1.0):
    """Orientation error at true rotations when one parameter is believed off its true value.

    The readings are those of the true mechanism ``p`` at rotations R; forward kinematics
    with ``p`` changed by ``delta`` in parameter ``name`` gives the orientation the
    controller would compute.

    Parameters
    ----------
    R : array_like, shape (m, 3, 3)
        True plate rotations.
    p : array_like, shape (20,)
        True parameters (mm, mm/V).
    name : str
        The parameter believed wrong, one of
        :data:`~loopcal.calibration.parameters.NAMES`.
    delta : float, default 1.0
        How far it is believed off, in its unit.

    Returns
    -------
    OrientationError

    Raises
    ------
    InputError, ParameterError
        Bad rotations, parameters or name.
    """
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
