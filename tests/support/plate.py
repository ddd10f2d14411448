"""Readings of a plate moved by hand, as synthetic volts: no mechanism, no DAQ (shared by
the calibration tests and the worker's synthetic recordings)."""

from __future__ import annotations

import numpy as np


def held_and_moved(rng: np.random.Generator, n: int, *, hold: tuple[int, int],
                   move: tuple[int, int], noise: float = 0.04) -> np.ndarray:  # fmt: skip
    """(n, 4) volts of a plate held still (``hold`` scans, drawn from [lo, hi)) and moved in
    a straight line to a new level in -8..8 V (``move`` scans) in turn, with white noise of
    ``noise`` V."""
    V = np.empty((n, 4))
    i, level = 0, rng.uniform(-8, 8, 4)
    while i < n:
        h = int(rng.integers(*hold))
        V[i : i + h] = level
        i += h
        if i >= n:
            break
        m = int(rng.integers(*move))
        target = rng.uniform(-8, 8, 4)
        V[i : i + m] = np.linspace(level, target, m + 2)[1:-1][: n - i]
        i, level = i + m, target
    return V + rng.normal(0, noise, V.shape)
