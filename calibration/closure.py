"""Loop closure of still poses at given parameters, and which sensor's offset moved.

With four sensors for three degrees of freedom, every still pose tells whether the loops
still close at the parameters in force. At parameters p, forward kinematics places the
plate; what is left of the readings orthogonal to every rotation
(:mod:`loopcal.calibration.implicit`: the unit vector q_k orthogonal to the columns of the pose's
whitened rotation Jacobian) is the pose's loop-closure error::

    e_k = q_k^T W_k (V_k - Vhat_k(R_k; p)),     W_k = diag(1 / sigma_ki),

N(0, 1) when the parameters are right and sigma_ki is the noise of the pose's mean reading.
If sensor i's offset has moved by delta mm, sensor i reads ``-delta / S_i`` V differently
and ``e_k = h_ki delta + noise`` with ``h_ki = -q_ki / (sigma_ki S_i)``. The pattern h_i
across poses differs from sensor to sensor (q_k turns with the pose), which is what
attributes a shift to one sensor.

The parameters in force are themselves uncertain (a calibration has standard deviations):
an error ``dp`` adds ``a_k^T dp`` to e_k (a_k the pose's information row). Over a window of
poses the errors are therefore correlated, with covariance ``Sigma = I + A C A^T`` (C the
parameters' covariance), and the generalised likelihood-ratio test of "sensor i moved" is::

    z_i = h_i^T Sigma^-1 e,   F_i = h_i^T Sigma^-1 h_i,   delta_i = z_i / F_i,
    T_i = z_i^2 / F_i ~ chi^2(1) when nothing moved,

with standard error ``1 / sqrt(F_i)`` on delta_i. A shift that began within the window
(a step, a creep) is tested at every change point: h_i is zero for the poses before it,
which then serve as the reference; the alarm threshold accounts for the number of change
points tried.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular
from scipy.special import chdtri

from . import implicit
from .errors import InputError
from .parameters import N_PARAMS, SL_GAIN, check_vector
from .residuals import check_volts


@dataclass(frozen=True)
class Closure:
    """Loop closure of m poses at the parameters in force (result of :func:`loop_closure`).

    Attributes
    ----------
    error : ndarray, shape (m,)
        Whitened loop-closure errors e_k (N(0, 1) if nothing moved).
    offset_pattern : ndarray, shape (m, 4)
        h_ki, the change of e_k per mm of shift of sensor i's offset, 1/mm.
    information : ndarray, shape (m, 20)
        a_k, the change of e_k per unit change of each parameter (per mm, per mm/V).
    usable : ndarray of bool, shape (m,)
        False for poses whose rotation the lengths do not determine (their rows are zero).
    """

    error: np.ndarray
    offset_pattern: np.ndarray
    information: np.ndarray
    usable: np.ndarray

    def __len__(self) -> int:
        return len(self.error)


@dataclass(frozen=True)
class PoseModels:
    """What the parameters in force predict for each of m poses, independent of the noise.

    A monitor testing a sliding window of poses computes each pose's once
    (:func:`pose_models`) and stacks them (:meth:`stack`); indexing with an int, a slice or
    an index array gives the models of those poses.

    Attributes
    ----------
    R : ndarray, shape (m, 3, 3)
        Plate rotations from forward kinematics.
    usable : ndarray of bool, shape (m,)
        Whether forward kinematics determines each pose's rotation
        (:func:`loopcal.calibration.implicit.start_rotations`).
    vhat : ndarray, shape (m, 4)
        The model's readings, V.
    Jp : ndarray, shape (m, 4, 20)
        Their derivatives with respect to the parameters.
    Jr : ndarray, shape (m, 4, 3)
        Their derivatives with respect to the rotation, V/rad
        (:func:`loopcal.calibration.implicit.model_jacobians`).
    """

    R: np.ndarray
    usable: np.ndarray
    vhat: np.ndarray
    Jp: np.ndarray
    Jr: np.ndarray

    @staticmethod
    def stack(models: list[PoseModels]) -> PoseModels:
        """Concatenate the models of several pose sets, in order.

        Parameters
        ----------
        models : list of PoseModels
            At least one.

        Returns
        -------
        PoseModels
        """
        return PoseModels(*(np.concatenate(x) for x in zip(
            *((m.R, m.usable, m.vhat, m.Jp, m.Jr) for m in models), strict=True)))  # fmt: skip

    def __getitem__(self, k: int | slice | np.ndarray) -> PoseModels:
        if isinstance(k, int):
            k = slice(k, k + 1)
        return PoseModels(self.R[k], self.usable[k], self.vhat[k], self.Jp[k], self.Jr[k])


def pose_models(volts: np.ndarray, p: np.ndarray) -> PoseModels:
    """What the parameters p predict for poses with the given mean readings.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        Mean readings, V.
    p : array_like, shape (20,)
        Parameters in force (mm, mm/V).

    Returns
    -------
    PoseModels

    Raises
    ------
    InputError, ParameterError
        Bad readings or parameters.
    """
    V = check_volts(volts)
    p = check_vector(p)
    R, ok = implicit.start_rotations(V, p)
    vhat, Jp, Jr = implicit.model_jacobians(R, p)
    return PoseModels(R, np.asarray(ok, dtype=bool), vhat, Jp, Jr)


def loop_closure(
    volts: np.ndarray,
    p: np.ndarray,
    sigma_volts: np.ndarray,
    *,
    models: PoseModels | None = None,
) -> Closure:
    """The loop-closure errors of still poses.

    Parameters
    ----------
    volts : array_like, shape (m, 4)
        Mean readings, V, as in :func:`pose_models`.
    p : array_like, shape (20,)
        Parameters in force (mm, mm/V), as in :func:`pose_models`.
    sigma_volts : array_like, shape (m, 4) or (4,)
        Standard deviation of each mean reading, V (one scan's noise over the square root
        of the scans averaged, with the converter's rounding:
        :func:`~loopcal.calibration.poses.pose_noise_volts`).
    models : PoseModels, optional
        The poses' :func:`pose_models` at ``p``, if already known (they do not depend on
        the noise).

    Returns
    -------
    Closure
        Errors, offset patterns and information rows; zero for unusable poses.

    Raises
    ------
    InputError
        Bad readings, or a ``sigma_volts`` not positive and finite.
    ParameterError
        If ``p`` fails :func:`~loopcal.calibration.parameters.check_vector`.
    """
    V = check_volts(volts)
    p = check_vector(p)
    sigma = np.broadcast_to(np.asarray(sigma_volts, dtype=float), V.shape)
    if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
        raise InputError("sigma_volts must be positive and finite")
    pm = pose_models(V, p) if models is None else models
    w = 1.0 / sigma
    q = implicit.loop_direction(pm.Jr * w[..., None])
    e = np.einsum("mi,mi->m", q, (V - pm.vhat) * w)
    a = -np.einsum("mrn,mr->mn", pm.Jp * w[..., None], q)
    h = -q * w / p[SL_GAIN]
    ok = pm.usable & np.isfinite(e)
    zero = ~ok
    e[zero], h[zero], a[zero] = 0.0, 0.0, 0.0
    return Closure(e, h, a, ok)


@dataclass(frozen=True)
class DriftTest:
    """The likelihood-ratio test of "sensor i's offset moved" over a window of poses.

    ``shift_mm``, ``std_mm`` and ``statistic`` are those at the change point that explains
    the loops best, if several were tried.

    Attributes
    ----------
    shift_mm : ndarray, shape (4,)
        Estimated shift of each sensor's offset, mm.
    std_mm : ndarray, shape (4,)
        Their standard errors, mm.
    statistic : ndarray, shape (4,)
        T_i, chi^2(1) when nothing moved.
    affected : int
        How many of the latest poses that change point leaves shifted.
    shape : str
        ``"step"`` (the same shift on each of them) or ``"creep"`` (growing linearly from
        the change point; ``shift_mm`` is then the shift at the latest pose).
    margin : float
        The best sensor's statistic minus the best any other sensor reaches under any
        hypothesis (2 ln of their likelihood ratio: how clearly the pattern points at it).
    poses : int
        Usable poses in the window.
    chi2_rms : float
        RMS of the whitened errors (about 1 when nothing moved).
    """

    shift_mm: np.ndarray
    std_mm: np.ndarray
    statistic: np.ndarray
    affected: int
    shape: str
    margin: float
    poses: int
    chi2_rms: float

    @property
    def sensor(self) -> int:
        """1..4: the sensor that explains the loops best."""
        return int(np.argmax(self.statistic)) + 1


def drift_test(
    closure: Closure,
    covariance: np.ndarray | None = None,
    *,
    change_points: bool = False,
    creep: bool = False,
) -> DriftTest:
    """Test every sensor for an offset shift over the poses of ``closure`` (oldest first).

    Parameters
    ----------
    closure : Closure
        The window's loop closure; unusable poses are left out.
    covariance : array_like, shape (20, 20), optional
        Covariance of the parameters in force (mm, mm/V squared); None takes them as exact.
    change_points : bool, default False
        False tests a shift of all the poses; True tests a shift of the latest k poses for
        every k (a change that began within the window: the poses before it are the
        reference), and reports the change point with the largest statistic (m hypotheses
        per sensor).
    creep : bool, default False
        With change points, also test a shift growing linearly over the latest k poses
        (2 m hypotheses per sensor; it fits a step almost as well, so it blurs which sensor
        moved).

    Returns
    -------
    DriftTest
        With NaN shifts and zero statistics if no pose is usable.

    Raises
    ------
    InputError
        If ``covariance`` is not (20, 20).

    Notes
    -----
    The statistic is the generalised likelihood-ratio test of the module docstring,
    ``T_i = z_i^2 / F_i`` with the errors whitened by ``Sigma = I + A C A^T``.
    """
    use = closure.usable
    e = closure.error[use]
    H = closure.offset_pattern[use]
    m = len(e)
    if m == 0:
        nan = np.full(4, np.nan)
        return DriftTest(nan, nan, np.zeros(4), 0, "step", 0.0, m, float("nan"))
    Sigma = np.eye(m)
    if covariance is not None:
        C = np.asarray(covariance, dtype=float)
        if C.shape != (N_PARAMS, N_PARAMS):
            raise InputError(f"covariance must be ({N_PARAMS}, {N_PARAMS}), got {C.shape}")
        A = closure.information[use]
        Sigma = Sigma + A @ C @ A.T
    L = np.linalg.cholesky(Sigma)
    ew = solve_triangular(L, e, lower=True)
    onsets = np.arange(m) if change_points else np.zeros(1, dtype=int)
    # the pattern of a shift that began at pose o: zero before it; a step, or a ramp that
    # reaches the estimated shift at the latest pose
    k = np.arange(m)[None, :]
    o = onsets[:, None]
    step = (k >= o).astype(float)  # (O, m)
    ramp = step * (k - o + 1) / (m - o)
    masks = np.concatenate([step, ramp]) if change_points and creep else step
    shapes = ["step"] * len(onsets) + (["creep"] * len(onsets) if change_points and creep else [])
    onsets = np.concatenate([onsets, onsets]) if change_points and creep else onsets
    Hm = masks[:, :, None] * H[None]  # (O, m, 4)
    # one triangular solve for every hypothesis at once: (m, O * 4) right-hand sides
    Hw = solve_triangular(L, Hm.transpose(1, 0, 2).reshape(m, -1), lower=True)
    Hw = Hw.reshape(m, len(masks), 4).transpose(1, 0, 2)  # (O, m, 4)
    z = np.einsum("omi,m->oi", Hw, ew)
    F = np.einsum("omi,omi->oi", Hw, Hw)
    with np.errstate(divide="ignore", invalid="ignore"):
        T = np.where(F > 0, z * z / F, 0.0)
    b = int(np.argmax(T.max(axis=1)))  # the hypothesis that explains the loops best
    with np.errstate(divide="ignore", invalid="ignore"):
        shift = z[b] / F[b]
        std = 1.0 / np.sqrt(F[b])
    rms = float(np.sqrt(np.mean(ew * ew)))
    best = int(np.argmax(T[b]))
    others = np.delete(T.max(axis=0), best)
    margin = float(T[b, best] - others.max())
    return DriftTest(shift, std, T[b], int(m - onsets[b]), shapes[b], margin, m, rms)


def threshold(false_alarm: float, tests: int = 4) -> float:
    """The statistic an alarm needs for a given false-alarm probability (Bonferroni).

    Parameters
    ----------
    false_alarm : float
        Probability, in (0, 1), that the largest of ``tests`` chi^2(1) statistics exceeds
        the threshold when nothing moved.
    tests : int, default 4
        Statistics compared: four sensors, times the change points tried.

    Returns
    -------
    float
        The chi^2(1) quantile of upper tail ``false_alarm / tests``.

    Raises
    ------
    InputError
        If ``false_alarm`` is not in (0, 1).
    """
    if not 0 < false_alarm < 1:
        raise InputError(f"false_alarm must lie in (0, 1), got {false_alarm}")
    return float(chdtri(1, false_alarm / tests))  # the chi-square(1) quantile


def step_tests(
    error: np.ndarray,
    offset_pattern: np.ndarray,
    information: np.ndarray,
    usable: np.ndarray,
    covariance: np.ndarray | None = None,
) -> list[DriftTest]:
    """:func:`drift_test` with ``change_points=True`` (steps only) over B windows of m poses
    at once, vectorised over the windows (a monitor replaying a day tests 30,000 windows).

    Parameters
    ----------
    error : array_like, shape (B, m)
    offset_pattern : array_like, shape (B, m, 4)
    information : array_like, shape (B, m, 20)
    usable : array_like of bool, shape (B, m)
        Each window's :class:`Closure` arrays stacked, oldest pose first.
    covariance : array_like, shape (20, 20), optional
        Covariance of the parameters in force; None takes them as exact.

    Returns
    -------
    list of DriftTest
        B tests, equal to ``drift_test`` of each window to rounding.

    Raises
    ------
    InputError
        If the shapes do not match, or ``covariance`` is not (20, 20).

    Notes
    -----
    Instead of one triangular solve per hypothesis, with ``S = Sigma^-1`` and ``u = S e``:
    ``z_oi = sum_{k>=o} H_ki u_k`` is a suffix sum, and ``F_oi = sum_{k,l>=o} H_ki S_kl H_li``
    grows from the latest pose back by ``G_oo + 2 sum_{l>o} G_ol`` (``G = H_i S H_i``,
    symmetric). Windows with unusable poses (their rows zero) go through
    :func:`drift_test`, which leaves them out.
    """
    e = np.asarray(error, dtype=float)
    H = np.asarray(offset_pattern, dtype=float)
    A = np.asarray(information, dtype=float)
    ok = np.asarray(usable, dtype=bool)
    if e.ndim != 2 or H.shape != e.shape + (4,) or A.shape != e.shape + (N_PARAMS,) \
            or ok.shape != e.shape:  # fmt: skip
        raise InputError("step_tests needs error (B, m), offset_pattern (B, m, 4), "
                         f"information (B, m, {N_PARAMS}) and usable (B, m)")  # fmt: skip
    n_win, m = e.shape
    out: list[DriftTest | None] = [None] * n_win
    whole = ok.all(axis=1)
    for b in np.flatnonzero(~whole):
        out[b] = drift_test(Closure(e[b], H[b], A[b], ok[b]), covariance, change_points=True)
    idx = np.flatnonzero(whole)
    if len(idx) and m:
        e, H, A = e[idx], H[idx], A[idx]
        Sigma = np.broadcast_to(np.eye(m), (len(idx), m, m)).copy()
        if covariance is not None:
            C = np.asarray(covariance, dtype=float)
            if C.shape != (N_PARAMS, N_PARAMS):
                raise InputError(f"covariance must be ({N_PARAMS}, {N_PARAMS}), got {C.shape}")
            Sigma += np.einsum("bkn,nj,blj->bkl", A, C, A, optimize=True)
        S = np.linalg.inv(Sigma)
        S = 0.5 * (S + S.transpose(0, 2, 1))
        u = np.einsum("bkl,bl->bk", S, e)
        z = np.flip(np.cumsum(np.flip(H * u[:, :, None], 1), 1), 1)  # (B, m onsets, 4)
        G = np.einsum("bki,bkl,bli->bikl", H, S, H)  # (B, 4, m, m)
        rows = np.einsum("bikk->bik", G) + 2 * np.triu(G, 1).sum(-1)
        F = np.flip(np.cumsum(np.flip(rows, 2), 2), 2).transpose(0, 2, 1)  # (B, m, 4)
        with np.errstate(divide="ignore", invalid="ignore"):
            T = np.where(F > 0, z * z / F, 0.0)
            best_o = np.argmax(T.max(axis=2), axis=1)  # (B,)
            r = np.arange(len(idx))
            zb, Fb, Tb = z[r, best_o], F[r, best_o], T[r, best_o]
            shift, std = zb / Fb, 1.0 / np.sqrt(Fb)
        rms = np.sqrt(np.einsum("bk,bk->b", u, e) / m)
        best_i = np.argmax(Tb, axis=1)
        others = T.max(axis=1)
        others[r, best_i] = -np.inf
        margin = Tb[r, best_i] - others.max(axis=1)
        for j, b in enumerate(idx):
            out[b] = DriftTest(shift[j], std[j], Tb[j], int(m - best_o[j]), "step",
                               float(margin[j]), m, float(rms[j]))  # fmt: skip
    return out  # type: ignore[return-value]
