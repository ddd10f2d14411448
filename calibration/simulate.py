"""Simulated poses of the reachable workspace, for tests, benchmarks and the emulated DAQ.

The sensor model follows docs/model.md section 2 and the DAQ's 12-bit converter: a true length d
gives ``V = (d - d0) / S``; Gaussian noise (default 40 mV, 1 sigma) is added; the converter
quantises with ``code = clamp(floor((V + 10) * 4096 / 20), 0, 4095)`` and the reading is
reconstructed at mid-code, ``(code + 0.5) * 20 / 4096 - 10``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .kinematics import (
    from_euler_zyz,
    in_stroke,
    inverse_kinematics,
    lengths_to_volts,
    plate_points,
)
from .parameters import (
    NOMINAL,
    PAPER7,
    SL_OFFSET,
    STROKE_MM,
    ParameterModel,
    check_vector,
    index_of,
)
from .residuals import loop_residuals

MAX_TILT_DEG = 45.0
MAX_SWIVEL_DEG = 90.0
NOISE_VOLTS = 0.040
# Poses whose mirror plate positions come closer than this, in any loop, are near-singular.
NEAR_SINGULAR_MM = 10.0


def quantize_volts(
    volts: np.ndarray, *, bits: int = 12, v_min: float = -10.0, v_max: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """Ideal floor-type ADC: returns (codes as int64, mid-code reconstruction in V)."""
    levels = 1 << bits
    span = v_max - v_min
    codes = np.clip(np.floor((np.asarray(volts) - v_min) * levels / span), 0, levels - 1)
    return codes.astype(np.int64), (codes + 0.5) * span / levels + v_min


def sample_rotations(
    n: int,
    rng: np.random.Generator,
    *,
    max_tilt_deg: float = MAX_TILT_DEG,
    max_swivel_deg: float = MAX_SWIVEL_DEG,
) -> np.ndarray:
    """n rotations with the output axis uniform over the cap ``tilt <= max_tilt_deg`` and the
    swivel (alpha + gamma) uniform in ``+-max_swivel_deg``. Returns (n, 3, 3)."""
    alpha = rng.uniform(-np.pi, np.pi, n)
    beta = np.arccos(rng.uniform(np.cos(np.radians(max_tilt_deg)), 1.0, n))
    swivel = rng.uniform(-np.radians(max_swivel_deg), np.radians(max_swivel_deg), n)
    return from_euler_zyz(np.column_stack([alpha, beta, swivel - alpha]))


def reachable(
    R: np.ndarray, p: np.ndarray, *, margin_mm: float = NEAR_SINGULAR_MM, stroke_mm=STROKE_MM
) -> np.ndarray:
    """(m,) bool: all four lengths inside the stroke and every loop at least ``margin_mm``
    from a branch merge (near-singular configurations are outside the usable workspace)."""
    d = inverse_kinematics(R, p)
    ok = in_stroke(d, p, stroke_mm).all(axis=1)
    res = loop_residuals(p, lengths_to_volts(d, p), plate_points(R, p), jacobian=False)
    return ok & (res.separation.min(axis=1) >= margin_mm) & res.feasible.all(axis=1)


def sample_workspace(
    n: int, rng: np.random.Generator, p: np.ndarray = NOMINAL, **limits: float
) -> np.ndarray:
    """n rotations drawn uniformly (as in :func:`sample_rotations`) from the reachable
    workspace of the mechanism with parameters ``p``. Returns (n, 3, 3)."""
    if n < 0:
        raise InputError(f"number of poses must be non-negative, got {n}")
    margin = limits.pop("margin_mm", NEAR_SINGULAR_MM)
    out: list[np.ndarray] = []
    have = 0
    while have < n:
        R = sample_rotations(max(64, 4 * (n - have)), rng, **limits)
        R = R[reachable(R, p, margin_mm=margin)]
        out.append(R[: n - have])
        have += len(out[-1])
    return np.concatenate(out) if out else np.zeros((0, 3, 3))


@dataclass(frozen=True)
class PoseSet:
    """Simulated readings with their ground truth.

    volts: (m, 4) readings in V as the calibration sees them (noisy, quantised if asked);
    codes: (m, 4) converter codes, or None without quantisation; rotations: (m, 3, 3) true
    plate rotations; lengths: (m, 4) true actuator lengths, mm; truth: (20,) true parameters.
    """

    volts: np.ndarray
    codes: np.ndarray | None
    rotations: np.ndarray
    lengths: np.ndarray
    truth: np.ndarray

    def __len__(self) -> int:
        return len(self.volts)

    def subset(self, idx: np.ndarray) -> PoseSet:
        idx = np.asarray(idx)
        codes = None if self.codes is None else self.codes[idx]
        return PoseSet(self.volts[idx], codes, self.rotations[idx], self.lengths[idx], self.truth)


def readings(
    R: np.ndarray,
    truth: np.ndarray,
    rng: np.random.Generator,
    *,
    noise_volts: float = NOISE_VOLTS,
    quantize: bool = True,
) -> PoseSet:
    """Sensor readings of the mechanism ``truth`` at rotations R, with noise and quantisation."""
    truth = check_vector(truth)
    if noise_volts < 0 or not np.isfinite(noise_volts):
        raise InputError(f"noise must be a non-negative number of volts, got {noise_volts}")
    d = inverse_kinematics(R, truth)
    V = lengths_to_volts(d, truth)
    if noise_volts > 0:
        V = V + rng.normal(0.0, noise_volts, V.shape)
    codes = None
    if quantize:
        codes, V = quantize_volts(V)
    return PoseSet(V, codes, np.asarray(R), d, truth)


def simulate_poses(
    n: int,
    *,
    truth: np.ndarray | None = None,
    seed: int | np.random.Generator = 0,
    noise_volts: float = NOISE_VOLTS,
    quantize: bool = True,
    **limits: float,
) -> PoseSet:
    """n random poses of the reachable workspace read through noisy, quantised sensors.

    truth defaults to :func:`perturbed_truth` of the same seed; noise_volts is the 1-sigma
    noise per channel before quantisation; limits go to :func:`sample_workspace`.
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    truth = perturbed_truth(rng) if truth is None else check_vector(truth)
    return readings(
        sample_workspace(n, rng, truth, **limits), truth, rng,
        noise_volts=noise_volts, quantize=quantize,
    )  # fmt: skip


def perturbed_truth(
    rng: np.random.Generator,
    *,
    offsets_mm: float = 3.0,
    geometry_mm: float = 0.5,
    model: ParameterModel | None = None,
    base: np.ndarray = NOMINAL,
) -> np.ndarray:
    """A plausible real mechanism: offsets moved uniformly within ``+-offsets_mm`` (a refitted
    LVDT), and the non-offset free parameters of ``model`` (default: the paper's set) within
    ``+-geometry_mm``, ties respected. Everything else stays at ``base``."""
    model = model or PAPER7
    p = np.array(base, dtype=float)
    x = model.free_values(p)
    for j, name in enumerate(model.free):
        is_offset = SL_OFFSET.start <= index_of(name) < SL_OFFSET.stop
        x[j] += rng.uniform(-1, 1) * (offsets_mm if is_offset else geometry_mm)
    p = model.expand(x, p)
    return check_vector(p)
