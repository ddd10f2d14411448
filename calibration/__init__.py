"""Closed-loop calibration of the redundant shoulder joint: pure numpy/scipy, no I/O.

From a stream of scans ``volts``, shape (n, 4) in V::

    from loopcal.calibration import calibrate, PAPER7, NOMINAL, still_poses
    result = calibrate(still_poses(volts).volts, PAPER7, NOMINAL).identification
    print(result.table())

The names listed in ``__all__`` are importable from here; each is documented in its module.
"""

import lazy_loader as lazy

# The API is imported on first use (PEP 562, by lazy_loader), so that ``from
# loopcal.calibration.errors import ...`` or a command that needs one module does not pay for
# scipy everywhere.
__getattr__, __dir__, __all__ = lazy.attach(
    __name__,
    submod_attrs={
        "errors": ["CalibrationError", "ConvergenceError", "InputError", "ParameterError",
                   "UnobservableError"],
        "identify": ["METHODS", "Identification", "identify"],
        "implicit": ["cramer_rao"],
        "kinematics": ["euler_zyz", "forward_kinematics", "inverse_kinematics"],
        "observability": ["analyse_identifiability", "observability_indices"],
        "parameters": ["NAMES", "NOMINAL", "PAPER7", "PRESETS", "ParameterModel", "Tie"],
        "pipeline": ["Calibration", "calibrate"],
        "poses": ["still_poses"],
        "selection": ["candidate_jacobian", "ml_candidates", "select_poses"],
        "simulate": ["simulate_poses"],
    },
)  # fmt: skip
