"""A simulated shoulder joint as the analog source of the emulated module.

Each conversion samples the plate's orientation at the channel's own instant (channels are
converted 250 us apart, so a moving plate skews a scan), computes the actuator lengths with
calibration's inverse kinematics for the *true* parameters, turns them into the LVDT
voltages ``V = (d - d0) / S`` and adds seeded Gaussian noise. The module quantises.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from loopcal.calibration.kinematics import inverse_kinematics, lengths_to_volts
from loopcal.calibration.parameters import NAMES, ParameterModel, check_vector, from_dict
from loopcal.calibration.simulate import NOISE_VOLTS, perturbed_truth

from .drift import OffsetDrift, offset_shift
from .scenarios import Scenario

_DIAG = np.arange(4)


def true_parameters(
    seed: int = 0, offset_error_mm: float = 3.0, overrides: Mapping[str, float] | None = None
) -> np.ndarray:
    """The simulated mechanism's true parameters (20,): the offsets (and the paper's seven
    parameters' geometry) moved at random from the blueprint by ``seed`` (offsets by up to
    ``offset_error_mm``), then explicit ``{NAME: value}`` overrides (mm, as in the config)."""
    if not (np.isfinite(offset_error_mm) and offset_error_mm >= 0):
        raise ValueError(f"offset error must be >= 0 mm, got {offset_error_mm!r}")
    rng = np.random.default_rng([seed, 1])
    p = perturbed_truth(rng, offsets_mm=offset_error_mm, model=ParameterModel.parse("paper7"))
    overrides = dict(overrides or {})
    unknown = sorted(set(overrides) - set(NAMES))
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(map(repr, unknown))}: the 20 are {', '.join(NAMES)}"
        )
    for name, value in overrides.items():
        if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value):
            raise ValueError(f"true parameter {name}: {value!r} is not a finite number")
    return from_dict({k: float(v) for k, v in overrides.items()}, p)


class MechanismSource:
    """:class:`~loopcal.simulator.source.SignalSource` of a simulated mechanism.

    scenario: the plate's motion; truth: the mechanism's true parameters (20,);
    noise_volts: 1-sigma noise per conversion; seed: the noise stream; drifts: offset
    drifts of the sensors (:mod:`loopcal.simulator.drift`); more can be added later to
    :attr:`drifts` (they act from their own start times).
    """

    def __init__(
        self,
        scenario: Scenario,
        truth: np.ndarray,
        *,
        noise_volts: float = NOISE_VOLTS,
        seed: int = 0,
        drifts: tuple[OffsetDrift, ...] = (),
    ) -> None:
        if not np.isfinite(noise_volts) or noise_volts < 0:
            raise ValueError(f"noise must be a non-negative number of volts, got {noise_volts}")
        self.scenario = scenario
        self.truth = check_vector(truth).copy()
        self.noise_volts = float(noise_volts)
        self._rng = np.random.default_rng(seed)
        self.drifts: list[OffsetDrift] = list(drifts)

    def clean(self, t: np.ndarray) -> np.ndarray:
        """Noise-free volts of the four channels at their instants t (4,)."""
        t = np.asarray(t, dtype=float)
        R = self.scenario.rotation(t)  # one rotation per channel
        d = inverse_kinematics(R, self.truth)[_DIAG, _DIAG]  # channel i at its own instant
        if self.drifts:
            d = d - offset_shift(self.drifts, t)
        return lengths_to_volts(d, self.truth)

    def convert(self, t: np.ndarray) -> np.ndarray:
        return self.clean(t) + self._rng.normal(0.0, self.noise_volts, 4)


class ReplaySource:
    """:class:`~loopcal.simulator.source.SignalSource` replaying a recording: each channel reads the
    latest recorded value at or before its instant (sample and hold), the recording starting
    at source time 0; after the end it holds the last value, or starts over with ``loop``.

    times_s: (n,) increasing recording times, s; volts: (n, 4). Recorded codes replay
    bit for bit when given as their mid-code volts (:func:`loopcal.drivers.ldq412.code_to_volts`).
    """

    def __init__(self, times_s: np.ndarray, volts: np.ndarray, *, loop: bool = False) -> None:
        self.times = np.asarray(times_s, dtype=float)
        self.volts = np.asarray(volts, dtype=float)
        if self.times.ndim != 1 or self.volts.shape != (len(self.times), 4) or not len(self.times):
            raise ValueError("a replay needs n increasing times and (n, 4) volts, n >= 1")
        if np.any(np.diff(self.times) <= 0):
            raise ValueError("replay times must increase strictly")
        self.times = self.times - self.times[0]
        self.loop = loop
        self.span = self.times[-1] + (np.median(np.diff(self.times)) if len(self.times) > 1 else 1)

    def convert(self, t: np.ndarray) -> np.ndarray:
        rel = np.asarray(t, dtype=float)
        if self.loop:
            rel = np.mod(rel, self.span)
        k = np.clip(np.searchsorted(self.times, rel, side="right") - 1, 0, len(self.times) - 1)
        return self.volts[k, np.arange(4)]

    @classmethod
    def from_truth_file(cls, path, *, loop: bool = False) -> ReplaySource:
        """Replay the scans of a ``loopcal simulate --truth-out`` file (every power-on in
        order; times from the scans' own source times)."""
        import json

        from loopcal.drivers.ldq412 import code_to_volts

        times, codes = [], []
        with open(path, encoding="utf-8") as fh:
            for n, line in enumerate(fh, 1):
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError as exc:
                    raise ValueError(f"{path}:{n}: not JSON ({exc.msg})") from None
                if rec.get("type") == "scan":
                    times.append(rec["t_s"])
                    codes.append(rec["codes"])
        if not times:
            raise ValueError(f"{path}: no scans to replay")
        return cls(np.array(times), code_to_volts(np.array(codes)), loop=loop)
