"""Scans of a simulated mechanism computed offline, as arrays: no emulator, no clock.

For benchmarks and tests that need hours of recording in seconds. The scans are the ones
the emulated module would make with the same scenario, truth, noise and seed (scan ``j`` at
``floor(j * 1e6 / rate)`` µs, channel ``i`` 250 µs after channel 1, oversampling 1), so a
recording written from them is what ``loopcal record`` would have recorded.
"""

from __future__ import annotations

import numpy as np

from loopcal.calibration.kinematics import inverse_kinematics, lengths_to_volts
from loopcal.calibration.parameters import check_vector
from loopcal.calibration.simulate import NOISE_VOLTS
from loopcal.drivers.ldq412 import CHANNEL_SKEW_S, N_CHANNELS, volts_to_code

from .drift import OffsetDrift, offset_shift
from .scenarios import Scenario

_CHUNK = 50_000
_DIAG = np.arange(N_CHANNELS)


def mechanism_scans(
    scenario: Scenario,
    truth: np.ndarray,
    n_scans: int,
    *,
    rate_hz: int = 20,
    noise_volts: float = NOISE_VOLTS,
    seed: int = 0,
    drifts: tuple[OffsetDrift, ...] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """The first ``n_scans`` scans after power-on, as arrays.

    The noise stream is the one :class:`~loopcal.simulator.mechanism.MechanismSource` draws
    with the same seed, so the codes equal the emulator's, scan for scan.

    Parameters
    ----------
    scenario : Scenario
        The plate's motion (:mod:`loopcal.simulator.scenarios`).
    truth : ndarray of float, shape (20,)
        The mechanism's true parameters (mm, mm/V).
    n_scans : int
        How many scans, from scan 0.
    rate_hz : int, default 20
        Scan rate, Hz.
    noise_volts : float, default NOISE_VOLTS
        Standard deviation of the noise per conversion, V (0.040 V).
    seed : int, default 0
        Seed of the noise stream.
    drifts : tuple of OffsetDrift, default ()
        Sensor offset drifts (:mod:`loopcal.simulator.drift`).

    Returns
    -------
    time_us : ndarray of int64, shape (n_scans,)
        Device time of each scan since power-on, µs: ``floor(j * 1e6 / rate_hz)``
        (unwrapped).
    codes : ndarray of int64, shape (n_scans, 4)
        Channel 1..4 codes, 0..4095.

    Raises
    ------
    ValueError
        If ``truth`` is not a valid parameter vector
        (:class:`~loopcal.calibration.errors.ParameterError`).

    Notes
    -----
    This is the emulator with its defaults: scan phase 0, no clock error, oversampling 1,
    no faults; the module's FIFO, counter wraps and status are not modelled.
    """
    p = check_vector(truth)
    rng = np.random.default_rng(seed)
    j = np.arange(n_scans, dtype=np.int64)
    time_us = j * 1_000_000 // rate_hz
    codes = np.empty((n_scans, N_CHANNELS), dtype=np.int64)
    skew = np.arange(N_CHANNELS) * CHANNEL_SKEW_S
    for a in range(0, n_scans, _CHUNK):
        b = min(a + _CHUNK, n_scans)
        t = (time_us[a:b] / 1e6)[:, None] + skew  # (m, 4): each channel at its own instant
        R = scenario.rotation(t.reshape(-1))
        d = inverse_kinematics(R, p).reshape(b - a, N_CHANNELS, N_CHANNELS)[:, _DIAG, _DIAG]
        if drifts:
            d = d - offset_shift(drifts, t)
        clean = lengths_to_volts(d, p)
        noise = rng.normal(0.0, noise_volts, (b - a, N_CHANNELS))
        codes[a:b] = volts_to_code(clean + noise)
    return time_us, codes
