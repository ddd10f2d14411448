"""Closed-loop calibration of the redundant shoulder joint: pure numpy/scipy, no I/O.

From a stream of scans ``volts``, shape (n, 4) in V::

    from loopcal.calibration import calibrate, PAPER7, NOMINAL, still_poses
    result = calibrate(still_poses(volts).volts, PAPER7, NOMINAL).identification
    print(result.table())

The names listed in ``__all__`` are importable from here; each is documented in its module.
"""

import importlib

from .errors import (
    CalibrationError,
    ConvergenceError,
    InputError,
    ParameterError,
    UnobservableError,
)

# The rest of the API is imported on first use (PEP 562), so that ``from calibration.errors
# import ...`` or a command that needs one module does not pay for scipy everywhere.
_LAZY = {
    "METHODS": "identify", "Identification": "identify", "identify": "identify",
    "cramer_rao": "implicit",
    "euler_zyz": "kinematics", "forward_kinematics": "kinematics",
    "inverse_kinematics": "kinematics",
    "analyse_identifiability": "observability", "observability_indices": "observability",
    "NAMES": "parameters", "NOMINAL": "parameters", "PAPER7": "parameters",
    "PRESETS": "parameters", "ParameterModel": "parameters", "Tie": "parameters",
    "Calibration": "pipeline", "calibrate": "pipeline",
    "still_poses": "poses",
    "candidate_jacobian": "selection", "ml_candidates": "selection", "select_poses": "selection",
    "simulate_poses": "simulate",
}  # fmt: skip


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


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
