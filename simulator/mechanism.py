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
from .source import NoisySource

_DIAG = np.arange(4)


def true_parameters(
    seed: int = 0, offset_error_mm: float = 3.0, overrides: Mapping[str, float] | None = None
) -> np.ndarray:
    """The simulated mechanism's true parameters, drawn from ``seed``.

    The offsets (and the paper's seven parameters' geometry) moved at random from the
    blueprint by ``seed`` (offsets by up to ``offset_error_mm``), then explicit
    ``{NAME: value}`` overrides.

    Parameters
    ----------
    seed : int, default 0
        Seed of the draw (:func:`loopcal.calibration.simulate.perturbed_truth` with the
        paper's seven free parameters: offsets uniform within ``+-offset_error_mm``, the
        free geometry within +-0.5 mm).
    offset_error_mm : float, default 3.0
        Largest offset error, mm, finite and >= 0.
    overrides : mapping of str to float, optional
        Parameters set exactly, by name (:data:`loopcal.calibration.parameters.NAMES`), in
        the config's units (mm, mm/V for the gains ``S1``..``S4``).

    Returns
    -------
    ndarray of float, shape (20,)
        The full parameter vector, in the order of
        :data:`loopcal.calibration.parameters.NAMES`.

    Raises
    ------
    ValueError
        If ``offset_error_mm`` is negative or not finite, or an override names an unknown
        parameter or is not a finite number (a bool is not a number here).

    Notes
    -----
    The overrides are not checked beyond that: a vector they make invalid (a gain <= 0,
    say) is refused later, by :class:`MechanismSource`.
    """
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


class MechanismSource(NoisySource):
    """:class:`~loopcal.simulator.source.SignalSource` of a simulated mechanism.

    Each conversion samples the plate's orientation at each channel's own instant, takes
    the four actuator lengths by inverse kinematics of the true parameters, subtracts the
    offset drifts, turns them into volts ``V = (d - d0) / S`` and adds noise (a
    :class:`~loopcal.simulator.source.NoisySource`).

    Parameters
    ----------
    scenario : Scenario
        The plate's motion (:mod:`loopcal.simulator.scenarios`).
    truth : ndarray of float, shape (20,)
        The mechanism's true parameters (:func:`true_parameters`; mm, mm/V).
    noise_volts : float, default NOISE_VOLTS
        Standard deviation of the Gaussian noise per conversion, V, >= 0 (the default,
        :data:`loopcal.calibration.simulate.NOISE_VOLTS`, is 0.040 V).
    seed : int, default 0
        Seed of the noise stream.
    drifts : tuple of OffsetDrift, default ()
        Offset drifts of the sensors (:mod:`loopcal.simulator.drift`).

    Attributes
    ----------
    scenario : Scenario
        As given.
    truth : ndarray of float, shape (20,)
        A copy of the true parameters.
    drifts : list of OffsetDrift
        The drifts; more can be appended later (each acts from its own start time).

    Raises
    ------
    ValueError
        If ``noise_volts`` is negative or not finite, or ``truth`` is not a valid
        parameter vector (:class:`~loopcal.calibration.errors.ParameterError`).
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
        self.drifts: list[OffsetDrift] = list(drifts)
        super().__init__(seed, noise_volts)

    @property
    def noise_volts(self) -> float:
        """Standard deviation of the noise per conversion, V, as given (read-only)."""
        return self._noise_sd

    def clean(self, t: np.ndarray) -> np.ndarray:
        """Channel i's volts for the plate's orientation at channel i's instant ``t[i]``,
        drifts included, V (:meth:`~loopcal.simulator.source.NoisySource.clean`)."""
        t = np.asarray(t, dtype=float)
        R = self.scenario.rotation(t)  # one rotation per channel
        d = inverse_kinematics(R, self.truth)[_DIAG, _DIAG]  # channel i at its own instant
        if self.drifts:
            d = d - offset_shift(self.drifts, t)
        return lengths_to_volts(d, self.truth)


class ReplaySource:
    """:class:`~loopcal.simulator.source.SignalSource` replaying recorded volts.

    Each channel reads the latest recorded value at or before its instant (sample and
    hold), the recording starting at source time 0; after the end it holds the last value,
    or starts over with ``loop``. Recorded codes replay bit for bit when given as their
    mid-code volts (:func:`loopcal.drivers.ldq412.code_to_volts`). This replays the analog
    inputs only; :mod:`loopcal.simulator.replay` replays a recording's scans themselves.

    Parameters
    ----------
    times_s : array_like of float, shape (n,)
        Recording times, s, strictly increasing, n >= 1 (shifted to start at 0).
    volts : array_like of float, shape (n, 4)
        Channel 1..4 volts at those times, V.
    loop : bool, default False
        Start over after the end (the span is the last time plus the median interval)
        instead of holding the last value.

    Attributes
    ----------
    times : ndarray of float, shape (n,)
        The times, s, shifted to start at 0.
    volts : ndarray of float, shape (n, 4)
        As given, V.
    loop : bool
        As given.
    span : float
        How long one pass lasts with ``loop``, s.

    Raises
    ------
    ValueError
        If the shapes do not match, there are no times, or they do not increase strictly.
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
        """One conversion: each channel's recorded value at or before its instant.

        Parameters
        ----------
        t : ndarray of float, shape (4,)
            Channel 1..4's instants, source time, s (before 0: the first value).

        Returns
        -------
        ndarray of float, shape (4,)
            Channel i's held value at channel i's instant, V (no noise added).
        """
        rel = np.asarray(t, dtype=float)
        if self.loop:
            rel = np.mod(rel, self.span)
        k = np.clip(np.searchsorted(self.times, rel, side="right") - 1, 0, len(self.times) - 1)
        return self.volts[k, np.arange(4)]

    @classmethod
    def from_truth_file(cls, path, *, loop: bool = False) -> ReplaySource:
        """Replay the scans of a ``loopcal simulate --truth-out`` file.

        Every power-on in order; times from the scans' own source times (``t_s``), codes as
        their mid-code volts.

        Parameters
        ----------
        path : str or os.PathLike
            The JSON Lines truth file (a header, then one ``{"type": "scan", ...}`` per scan).
        loop : bool, default False
            Start over after the end.

        Returns
        -------
        ReplaySource
            A source holding each scan's volts from its ``t_s`` on.

        Raises
        ------
        ValueError
            If a line is not JSON, the file holds no scans, or the scans' times do not
            increase strictly.
        OSError
            If the file cannot be read.
        """
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
