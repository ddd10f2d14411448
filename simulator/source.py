"""What the four LVDT conditioners present at the LDQ-412's inputs.

A :class:`SignalSource` is the analog world seen by the emulated module: the device model
calls :meth:`SignalSource.convert` once per conversion (so N times per scan with
oversampling N) with the four channel instants of the scan, and quantizes what it gets.

:class:`TestSource` is the built-in deterministic source used when the emulator is given
none: slow sines per channel plus seeded Gaussian noise. :class:`ConstantSource` holds
fixed voltages (with no noise): handy for pinning exact codes.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from loopcal.drivers.ldq412 import N_CHANNELS


@runtime_checkable
class SignalSource(Protocol):
    """The analog inputs of the module: anything with a :meth:`convert` method.

    :class:`TestSource`, :class:`ConstantSource`,
    :class:`~loopcal.simulator.mechanism.MechanismSource` and
    :class:`~loopcal.simulator.mechanism.ReplaySource` are the ones loopcal ships.
    """

    def convert(self, t: np.ndarray) -> np.ndarray:
        """Volts the four LVDT conditioners present at instants ``t``.

        Parameters
        ----------
        t : ndarray of float, shape (4,)
            Source time of each channel's conversion, s: channel i (0-based) at
            ``t_scan + i * 250e-6``. The device model passes seconds since the module's
            *first* power-on by the owner's clock (it keeps running through power cycles,
            as the LVDTs do; :mod:`loopcal.simulator.device`).

        Returns
        -------
        ndarray of float, shape (4,)
            Channel 1..4 volts, noise included (the module quantizes them; beyond +-10 V
            they clamp to the rail codes).

        Notes
        -----
        Called once per conversion, so N times per scan with oversampling N (with the same
        instants each time); must be deterministic for a given seed and call sequence.
        """
        ...


class NoisySource:
    """A :class:`SignalSource` whose conversions are its :meth:`clean` volts plus noise.

    The noise is Gaussian, from ``numpy.random.default_rng(seed)``: each conversion draws
    exactly four normals, so the noise stream depends only on the seed and the number of
    calls. Subclasses give :meth:`clean`.

    Parameters
    ----------
    seed : int
        Seed of the noise stream.
    noise_sd : float
        Standard deviation of the noise per conversion, V.
    """

    def __init__(self, seed: int, noise_sd: float) -> None:
        self._rng = np.random.default_rng(seed)
        self._noise_sd = float(noise_sd)

    def clean(self, t: np.ndarray) -> np.ndarray:
        """Channel 1..4's noise-free volts, shape (4,), V, at their instants ``t``, shape
        (4,), source time, s; draws no random numbers (each subclass gives its own)."""
        raise NotImplementedError

    def convert(self, t: np.ndarray) -> np.ndarray:
        """One conversion of the four channels (:meth:`SignalSource.convert`).

        Parameters
        ----------
        t : ndarray of float, shape (4,)
            Channel 1..4's instants, source time, s.

        Returns
        -------
        ndarray of float, shape (4,)
            :meth:`clean` plus four fresh normal draws of the noise's standard deviation, V.
        """
        return self.clean(t) + self._rng.normal(0.0, self._noise_sd, N_CHANNELS)


class TestSource(NoisySource):
    """Slow sines per channel plus Gaussian noise from ``numpy.random.default_rng(seed)``.

    Channel i: ``offset[i] + amplitude[i] * sin(2 pi freq[i] t + phase[i]) + N(0, noise_v)``.
    The defaults stay well inside ±10 V (no rail) and move by less than one code between
    the conversions of one scan (a :class:`NoisySource`: four normals a call). The
    emulator's source when it is given none.

    Parameters
    ----------
    seed : int, default 0
        Seed of the noise stream.
    amplitude_v : sequence of 4 float, default (4.0, 3.0, 5.0, 2.0)
        Sine amplitude per channel, V.
    freq_hz : sequence of 4 float, default (0.05, 0.07, 0.11, 0.13)
        Sine frequency per channel, Hz.
    offset_v : sequence of 4 float, default (0.5, -1.0, 0.0, 2.5)
        Level the sine swings about per channel, V.
    phase_rad : sequence of 4 float, default (0.0, 1.0, 2.0, 3.0)
        Sine phase at t = 0 per channel, rad.
    noise_v : float, default 0.005
        Standard deviation of the Gaussian noise per conversion, V.

    Attributes
    ----------
    amplitude_v : ndarray of float, shape (4,)
        As given, V.
    freq_hz : ndarray of float, shape (4,)
        As given, Hz.
    offset_v : ndarray of float, shape (4,)
        As given, V.
    phase_rad : ndarray of float, shape (4,)
        As given, rad.

    Raises
    ------
    ValueError
        If one of the four per-channel sequences does not have 4 values.
    """

    __test__ = False  # not a pytest test class, despite the name

    def __init__(
        self,
        seed: int = 0,
        *,
        amplitude_v: Sequence[float] = (4.0, 3.0, 5.0, 2.0),
        freq_hz: Sequence[float] = (0.05, 0.07, 0.11, 0.13),
        offset_v: Sequence[float] = (0.5, -1.0, 0.0, 2.5),
        phase_rad: Sequence[float] = (0.0, 1.0, 2.0, 3.0),
        noise_v: float = 0.005,
    ) -> None:
        self.amplitude_v = np.asarray(amplitude_v, dtype=float)
        self.freq_hz = np.asarray(freq_hz, dtype=float)
        self.offset_v = np.asarray(offset_v, dtype=float)
        self.phase_rad = np.asarray(phase_rad, dtype=float)
        for name in ("amplitude_v", "freq_hz", "offset_v", "phase_rad"):
            if getattr(self, name).shape != (N_CHANNELS,):
                raise ValueError(f"{name} needs {N_CHANNELS} values")
        super().__init__(seed, noise_v)

    @property
    def noise_v(self) -> float:
        """Standard deviation of the noise per conversion, V, as given (read-only)."""
        return self._noise_sd

    def clean(self, t: np.ndarray) -> np.ndarray:
        """``offset_v + amplitude_v * sin(2 pi freq_hz t + phase_rad)``, V, at instants ``t``
        (:meth:`NoisySource.clean`)."""
        t = np.asarray(t, dtype=float)
        return self.offset_v + self.amplitude_v * np.sin(
            2.0 * np.pi * self.freq_hz * t + self.phase_rad
        )


class ConstantSource:
    """Fixed volts on each channel, no noise: handy for pinning exact codes.

    Parameters
    ----------
    volts : sequence of 4 float
        Channel 1..4 volts, V.

    Attributes
    ----------
    volts : ndarray of float, shape (4,)
        What every conversion returns; it may be changed (or assigned) between scans.

    Raises
    ------
    ValueError
        If ``volts`` does not have 4 values.
    """

    def __init__(self, volts: Sequence[float]) -> None:
        self.volts = np.asarray(volts, dtype=float)
        if self.volts.shape != (N_CHANNELS,):
            raise ValueError(f"volts needs {N_CHANNELS} values")

    def convert(self, t: np.ndarray) -> np.ndarray:
        """One conversion: :attr:`volts`, whatever the instants.

        Parameters
        ----------
        t : ndarray of float, shape (4,)
            Each channel's instant, s (not used).

        Returns
        -------
        ndarray of float, shape (4,)
            A copy of :attr:`volts`, V.
        """
        return self.volts.copy()
