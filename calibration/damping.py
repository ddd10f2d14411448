"""The damping of a Levenberg-Marquardt iteration, as Nielsen updates it.

The paper's fit (:func:`loopcal.calibration.identify.identify`) and the maximum-likelihood
fit (:func:`loopcal.calibration.implicit.fit_linearised`) damp their steps by the same rule:
a step that lowers the misfit lowers the damping by the gain ratio rho (actual over
predicted reduction), to a third at most; a refused step raises it by a factor that doubles
with each refusal in a row (H. B. Nielsen, "Damping parameter in Marquardt's method",
IMM-REP-1999-05, DTU).
"""

from __future__ import annotations

from dataclasses import dataclass

#: damping at which no step is worth trying any more: the iteration has stalled
MAX_DAMPING = 1e12


@dataclass
class Damping:
    """The damping lam of one Levenberg-Marquardt run, updated step by step.

    Attributes
    ----------
    lam : float, default 1e-3
        The damping, a multiple of the normal matrix's diagonal (dimensionless).
    nu : float, default 2.0
        The factor of the next raise; doubled by each refusal in a row.
    """

    lam: float = 1e-3
    nu: float = 2.0

    @property
    def exhausted(self) -> bool:
        """Whether lam has reached :data:`MAX_DAMPING`: no step is worth trying."""
        return self.lam >= MAX_DAMPING

    def accept(self, rho: float) -> None:
        """Lower lam after a step taken with gain ratio ``rho > 0``.

        Parameters
        ----------
        rho : float
            Actual over predicted reduction of the misfit.
        """
        self.lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        self.nu = 2.0

    def refuse(self) -> None:
        """Raise lam after a refused step (no reduction, out of bounds, or not finite)."""
        self.lam *= self.nu
        self.nu *= 2.0
