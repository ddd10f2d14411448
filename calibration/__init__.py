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
from .identify import METHODS, Identification, identify
from .implicit import cramer_rao
from .kinematics import euler_zyz, forward_kinematics, inverse_kinematics
from .observability import analyse_identifiability, observability_indices
from .parameters import NAMES, NOMINAL, PAPER7, PRESETS, ParameterModel, Tie
from .pipeline import Calibration, calibrate
from .poses import still_poses
from .selection import candidate_jacobian, ml_candidates, select_poses
from .simulate import simulate_poses

__all__ = [
    "METHODS",
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
    "cramer_rao",
    "euler_zyz",
    "forward_kinematics",
    "identify",
    "inverse_kinematics",
    "ml_candidates",
    "observability_indices",
    "select_poses",
    "simulate_poses",
    "still_poses",
]
