"""What every scenario is: the base class of the plate's motions and the minimum-jerk move.

:class:`Scenario` maps device times to plate rotations; the scenarios themselves are in
:mod:`loopcal.simulator.scenarios` (a technician's hand, the plate held, a sweep) and
:mod:`loopcal.simulator.task` (the controller's task loop). Both import this module and
nothing of each other's, so that :mod:`~loopcal.simulator.scenarios` can name every scenario
(:data:`~loopcal.simulator.scenarios.SCENARIOS`).
"""

from __future__ import annotations

import numpy as np


class Scenario:
    """Base class: :meth:`rotation` of the plate at device times ``t``.

    Attributes
    ----------
    name : str
        The scenario's name (``loopcal simulate --scenario NAME``; a class attribute).
    """

    name = "scenario"

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """The plate's orientation at times ``t``.

        Parameters
        ----------
        t : array_like of float, shape (k,)
            Source times, s since the module's first power-on (a scalar is one time).

        Returns
        -------
        ndarray of float, shape (k, 3, 3)
            The plate's rotation matrix (plate frame in base frame) at each time.

        Raises
        ------
        NotImplementedError
            In the base class; every scenario overrides it.
        """
        raise NotImplementedError

    def describe(self) -> dict:
        """What the scenario is, for a truth file's header.

        Returns
        -------
        dict
            ``{"name": name}`` plus the scenario's settings (JSON-serialisable).
        """
        return {"name": self.name}


def min_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk progress ``10 tau^3 - 15 tau^4 + 6 tau^5`` of a move.

    Parameters
    ----------
    tau : array_like of float, any shape
        Fraction of the move's duration; clipped to [0, 1].

    Returns
    -------
    ndarray of float, same shape as ``tau``
        Fraction of the way covered, 0 to 1 (zero speed and acceleration at both ends).
    """
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)
