"""A simulated shoulder joint as the analog source of the emulated module.

Each conversion samples the plate's orientation at the channel's own instant (channels are
converted 250 us apart, so a moving plate skews a scan), computes the actuator lengths with
calibration's inverse kinematics for the *true* parameters, turns them into the LVDT
voltages ``V = (d - d0) / S`` and adds seeded Gaussian noise. The module quantises.
"""

from __future__ import annotations

import numpy as np

from calibration.kinematics import inverse_kinematics, lengths_to_volts
from calibration.parameters import check_vector
from calibration.simulate import NOISE_VOLTS

from .scenarios import Scenario

_DIAG = np.arange(4)


class MechanismSource:
    """:class:`~simulator.source.SignalSource` of a simulated mechanism.

    scenario: the plate's motion; truth: the mechanism's true parameters (20,);
    noise_volts: 1-sigma noise per conversion; seed: the noise stream.
    """

    def __init__(
        self,
        scenario: Scenario,
        truth: np.ndarray,
        *,
        noise_volts: float = NOISE_VOLTS,
        seed: int = 0,
    ) -> None:
        if not np.isfinite(noise_volts) or noise_volts < 0:
            raise ValueError(f"noise must be a non-negative number of volts, got {noise_volts}")
        self.scenario = scenario
        self.truth = check_vector(truth).copy()
        self.noise_volts = float(noise_volts)
        self._rng = np.random.default_rng(seed)

    def clean(self, t: np.ndarray) -> np.ndarray:
        """Noise-free volts of the four channels at their instants t (4,)."""
        R = self.scenario.rotation(np.asarray(t, dtype=float))  # one rotation per channel
        d = inverse_kinematics(R, self.truth)[_DIAG, _DIAG]  # channel i at its own instant
        return lengths_to_volts(d, self.truth)

    def convert(self, t: np.ndarray) -> np.ndarray:
        return self.clean(t) + self._rng.normal(0.0, self.noise_volts, 4)
