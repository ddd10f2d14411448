"""The calibration's defaults, in a module that imports nothing: what a command's ``--help``
prints (``loopcal calibrate``, ``observability``, ``demo``, ``simulate``) is read from here
without waiting for numpy and scipy, and the modules that use each default take it from
here too, so that it is written once.
"""

from __future__ import annotations

#: the free set a calibration identifies unless told otherwise: the paper's seven
#: (:data:`loopcal.calibration.parameters.PRESETS`)
DEFAULT_FREE = "paper7"

#: the estimators :func:`loopcal.calibration.identify.identify` knows: maximum likelihood,
#: and the paper's closed-loop residuals
METHODS = ("ml", "paper")
#: the estimator used when none is named: maximum likelihood reaches the Cramér-Rao bound
#: where the paper's method stays 1.2 to 1.5 times above it (bench/bench_ml.py)
DEFAULT_METHOD = "ml"

#: how many of the recorded still poses a calibration on poses selects unless told otherwise
#: (:func:`loopcal.calibration.pipeline.calibrate`; a fit on every scan selects none)
DEFAULT_N_SELECT = 50

#: the paper's acceptable condition number (docs/model.md section 11)
CONDITION_OK = 1000.0

#: the sensors' noise, 1 sigma, V (the paper's 40 mV)
NOISE_VOLTS = 0.040
