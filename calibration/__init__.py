"""Closed-loop calibration of the redundant shoulder joint: pure numpy/scipy, no I/O.

from calibration import calibrate, PAPER7, NOMINAL, still_poses
result = calibrate(still_poses(volts).volts, PAPER7, NOMINAL).identification
print(result.table())
"""

from .errors import (
    CalibrationError,
    ConvergenceError,
    InputError,
    ParameterError,
    UnobservableError,
)
from .identify import Identification, identify
from .kinematics import euler_zyz, forward_kinematics, inverse_kinematics
from .observability import analyse_identifiability, observability_indices
from .parameters import NAMES, NOMINAL, PAPER7, PRESETS, ParameterModel, Tie
from .pipeline import Calibration, calibrate
from .poses import still_poses
from .selection import candidate_jacobian, select_poses
from .simulate import simulate_poses

__all__ = [
    "NAMES",
    "NOMINAL",
    "PAPER7",
    "PRESETS",
    "Calibration",
    "CalibrationError",
    "ConvergenceError",
    "Identification",
    "InputError",
    "ParameterError",
    "ParameterModel",
    "Tie",
    "UnobservableError",
    "analyse_identifiability",
    "calibrate",
    "candidate_jacobian",
    "euler_zyz",
    "forward_kinematics",
    "identify",
    "inverse_kinematics",
    "observability_indices",
    "select_poses",
    "simulate_poses",
    "still_poses",
]
