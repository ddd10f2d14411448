"""The acceptance gates: when the worker may vouch for a calibration, and what to do if not.

Each gate compares one figure of the identification with a limit and, when it fails, says
why in plain words and what the technician should do about it (a :class:`Gate`).
``loopcal calibrate --write`` writes the controller config only if every gate passes.

The gates are a list, :data:`GATES` (:mod:`~loopcal.daemon.worker.gates.checks`): each
entry measures its figure from what the worker has (:class:`GateContext`), says whether it
applies to the kind of fit, and judges it; :func:`measure_gates` runs them. The judgements
live by kind: :mod:`~loopcal.daemon.worker.gates.samples` (``poses``),
:mod:`~loopcal.daemon.worker.gates.fit` (``converged``, ``condition``,
``min_singular``, ``plausible``, ``precision``) and
:mod:`~loopcal.daemon.worker.gates.residual` (``noise``, ``averaging``, ``gains``,
``holdout``). docs/calibration.md's table of gates explains each and its limits; a test
holds it to :data:`GATES` (every gate there, with the limits it uses).
"""

from __future__ import annotations

from .checks import GATES as GATES
from .checks import Check as Check
from .checks import GateContext as GateContext
from .checks import measure_gates as measure_gates
from .gate import Advice as Advice
from .gate import Gate as Gate
