"""Simulated poses of the reachable workspace, for tests, benchmarks and the emulated DAQ.

The sensor model follows docs/model.md section 2 and the DAQ's 12-bit converter: a true length d
gives ``V = (d - d0) / S``; Gaussian noise (default 40 mV, 1 sigma) is added; the converter
quantises with ``code = clamp(floor((V + 10) * 4096 / 20), 0, 4095)`` and the reading is
reconstructed at mid-code, ``(code + 0.5) * 20 / 4096 - 10``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .defaults import NOISE_VOLTS
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

#: largest tilt of the output axis sampled, deg
MAX_TILT_DEG = 45.0
#: largest swivel (alpha + gamma) sampled either way, deg
MAX_SWIVEL_DEG = 90.0
#: mm: poses whose mirror plate positions come closer than this, in any loop, are
#: near-singular
NEAR_SINGULAR_MM = 10.0


def quantize_volts(
    volts: np.ndarray, *, bits: int = 12, v_min: float = -10.0, v_max: float = 10.0
) -> tuple[np.ndarray, np.ndarray]:
    """Ideal floor-type ADC: ``code = clamp(floor((V - v_min) * 2^bits / span), 0, 2^bits - 1)``.

    Parameters
    ----------
    volts : array_like
        Voltages, V, any shape.
    bits : int, default 12
        Converter resolution.
    v_min, v_max : float, default -10.0, 10.0
        The converter's span, V; readings beyond it saturate.

    Returns
    -------
    codes : ndarray of int64
        Converter codes, the shape of ``volts``.
    volts : ndarray
        The mid-code reconstruction ``(code + 0.5) * span / 2^bits + v_min``, V.
    """
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
    """n random rotations: the output axis uniform over a spherical cap, the swivel uniform.

    Parameters
    ----------
    n : int
        Number of rotations.
    rng : numpy.random.Generator
        Source of randomness.
    max_tilt_deg : float, default MAX_TILT_DEG
        The cap ``tilt <= max_tilt_deg``, deg.
    max_swivel_deg : float, default MAX_SWIVEL_DEG
        The swivel (alpha + gamma) is uniform in ``+-max_swivel_deg``, deg.

    Returns
    -------
    ndarray, shape (n, 3, 3)
        Rotations; not checked against the workspace (:func:`sample_workspace` is).
    """
    alpha = rng.uniform(-np.pi, np.pi, n)
    beta = np.arccos(rng.uniform(np.cos(np.radians(max_tilt_deg)), 1.0, n))
    swivel = rng.uniform(-np.radians(max_swivel_deg), np.radians(max_swivel_deg), n)
    return from_euler_zyz(np.column_stack([alpha, beta, swivel - alpha]))


def reachable(
    R: np.ndarray, p: np.ndarray, *, margin_mm: float = NEAR_SINGULAR_MM, stroke_mm=STROKE_MM
) -> np.ndarray:
    """Which rotations lie in the usable workspace of the mechanism.

    Parameters
    ----------
    R : array_like, shape (m, 3, 3)
        Plate rotations.
    p : array_like, shape (20,)
        The mechanism's parameters (mm, mm/V).
    margin_mm : float, default NEAR_SINGULAR_MM
        Smallest branch separation of every loop, mm (near-singular configurations are
        outside the usable workspace).
    stroke_mm : float, default STROKE_MM
        Half the stroke, mm.

    Returns
    -------
    ndarray of bool, shape (m,)
        All four lengths inside ``d0 +- stroke_mm``, every loop feasible and at least
        ``margin_mm`` from a branch merge.
    """
    d = inverse_kinematics(R, p)
    ok = in_stroke(d, p, stroke_mm).all(axis=1)
    res = loop_residuals(p, lengths_to_volts(d, p), plate_points(R, p), jacobian=False)
    return ok & (res.separation.min(axis=1) >= margin_mm) & res.feasible.all(axis=1)


def sample_workspace(
    n: int, rng: np.random.Generator, p: np.ndarray = NOMINAL, **limits: float
) -> np.ndarray:
    """n rotations drawn uniformly from the reachable workspace of a mechanism.

    Draws as :func:`sample_rotations` does and keeps the :func:`reachable` ones until it
    has n.

    Parameters
    ----------
    n, rng
        As for :func:`sample_rotations`: how many, and the random generator.
    p : array_like, shape (20,), default NOMINAL
        The mechanism's parameters (mm, mm/V).
    **limits : float
        ``max_tilt_deg``, ``max_swivel_deg`` for :func:`sample_rotations`, and
        ``margin_mm`` for :func:`reachable`.

    Returns
    -------
    ndarray, shape (n, 3, 3)

    Raises
    ------
    InputError
        If n is negative.
    """
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

    Attributes
    ----------
    volts : ndarray, shape (m, 4)
        Readings as the calibration sees them (noisy, quantised if asked), V.
    codes : ndarray of int64, shape (m, 4), or None
        Converter codes; None without quantisation.
    rotations : ndarray, shape (m, 3, 3)
        True plate rotations.
    lengths : ndarray, shape (m, 4)
        True actuator lengths, mm.
    truth : ndarray, shape (20,)
        True parameters (mm, mm/V).
    """

    volts: np.ndarray
    codes: np.ndarray | None
    rotations: np.ndarray
    lengths: np.ndarray
    truth: np.ndarray

    def __len__(self) -> int:
        return len(self.volts)

    def subset(self, idx: np.ndarray) -> PoseSet:
        """The poses ``idx`` (indices or a boolean mask), with the same truth.

        Parameters
        ----------
        idx : array_like of int or bool

        Returns
        -------
        PoseSet
        """
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
    """Sensor readings of the mechanism ``truth`` at rotations R, with noise and quantisation.

    Parameters
    ----------
    R : array_like, shape (m, 3, 3)
        True plate rotations.
    truth : array_like, shape (20,)
        True parameters (mm, mm/V).
    rng : numpy.random.Generator
        Source of the noise.
    noise_volts : float, default NOISE_VOLTS
        Gaussian noise per channel, 1 sigma, V, added before quantisation.
    quantize : bool, default True
        Quantise with the 12-bit converter (:func:`quantize_volts`).

    Returns
    -------
    PoseSet

    Raises
    ------
    InputError
        Bad rotations, or a noise that is negative or not finite.
    ParameterError
        If ``truth`` fails :func:`~loopcal.calibration.parameters.check_vector`.
    """
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

    Parameters
    ----------
    n : int
        Number of poses.
    truth : array_like, shape (20,), optional
        The mechanism; default :func:`perturbed_truth` drawn from the same generator.
    seed : int or numpy.random.Generator, default 0
        Seed of a new generator, or a generator to draw from.
    noise_volts : float, default NOISE_VOLTS
        The 1-sigma noise per channel before quantisation, V.
    quantize : bool, default True
        Quantise with the 12-bit converter.
    **limits : float
        For :func:`sample_workspace`.

    Returns
    -------
    PoseSet

    Examples
    --------
    >>> from loopcal.calibration import simulate_poses, identify
    >>> ps = simulate_poses(100, seed=1)
    >>> result = identify(ps.volts)
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
    """A plausible real mechanism: the free parameters of a model moved at random.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    offsets_mm : float, default 3.0
        Free offsets move uniformly within ``+-offsets_mm`` (a refitted LVDT).
    geometry_mm : float, default 0.5
        The other free parameters move uniformly within ``+-geometry_mm`` (in their unit).
    model : ParameterModel, optional
        Which parameters move; default the paper's set, ties respected.
    base : array_like, shape (20,), default NOMINAL
        Everything else stays at ``base``.

    Returns
    -------
    ndarray, shape (20,)

    Raises
    ------
    ParameterError
        If the result fails :func:`~loopcal.calibration.parameters.check_vector`.
    """
    model = model or PAPER7
    p = np.array(base, dtype=float)
    x = model.free_values(p)
    for j, name in enumerate(model.free):
        is_offset = SL_OFFSET.start <= index_of(name) < SL_OFFSET.stop
        x[j] += rng.uniform(-1, 1) * (offsets_mm if is_offset else geometry_mm)
    p = model.expand(x, p)
    return check_vector(p)
