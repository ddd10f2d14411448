"""The robot's controller at work: the plate driven round a fixed task loop, for ever.

:class:`TaskLoop` is the operation scenario (``loopcal simulate --scenario task``): a few
fixed orientations (waypoints), drawn once from the seed, visited in turn by smooth
minimum-jerk moves with a dwell at each, and the loop repeated exactly. Unlike a
technician's hand (:class:`~loopcal.simulator.scenarios.HandMoves`) it never ends and never
varies: what a module sees between calibrations while the robot does its job.
"""

from __future__ import annotations

import numbers

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from loopcal.calibration.kinematics import euler_zyz, from_euler_zyz
from loopcal.calibration.parameters import NOMINAL
from loopcal.calibration.simulate import NEAR_SINGULAR_MM, reachable

from .motion import Scenario, min_jerk

#: largest tilt of the plate's output axis at a waypoint, degrees
MAX_TILT_DEG = 30.0
#: largest twist (swivel about the plate's own axis) at a waypoint, either way, degrees
MAX_TWIST_DEG = 25.0
#: draws of one waypoint before its tilt and twist are scaled down (each draw after that
#: shrinks them by 1/DRAWS more, toward home)
DRAWS = 40
#: orientations checked on each move's path (the shortest rotation) against the workspace
PATH_CHECKS = 48


class TaskLoop(Scenario):
    """The controller drives the plate round a fixed loop of waypoints, for ever.

    ``waypoints`` orientations are drawn once from ``seed``: waypoint ``i`` tilts the
    plate's output axis toward azimuth ``phase + 360 i / waypoints`` degrees (``phase``
    drawn, each azimuth jittered by up to a quarter of its sector), by 60 to 100 % of
    ``max_tilt_deg``, and twists it about its own axis by 40 to 100 % of
    ``max_twist_deg``, alternately one way and the other. The loop thus circles the base,
    tilting the plate toward every sensor in turn. Each waypoint, and each move's path
    between two consecutive ones (the shortest rotation, waypoint ``n - 1`` back to 0
    included), lies in ``params``' reachable workspace with a margin from singular
    configurations (a waypoint that does not is drawn again, after :data:`DRAWS` draws
    with its tilt and twist scaled down toward home).

    From time 0 the plate dwells ``dwell_s`` at waypoint 0, moves to waypoint 1 in
    ``move_s`` (a minimum-jerk profile along the shortest rotation: at rest at both
    ends), dwells there, and so on, back from waypoint ``n - 1`` to waypoint 0 and round
    again: exactly periodic, with period ``waypoints * (move_s + dwell_s)``. Before time 0
    the plate is at waypoint 0.

    Parameters
    ----------
    seed : int, default 0
        Seed of the waypoints.
    waypoints : int, default 5
        Number of waypoints, >= 2.
    move_s : float, default 2.0
        Duration of each move between consecutive waypoints, s, > 0.
    dwell_s : float, default 0.5
        How long the plate stays at each waypoint, s, >= 0 (0: no dwell; the plate is at
        rest only for an instant at each waypoint).
    params : ndarray of float, shape (20,), default NOMINAL
        The mechanism whose workspace the loop stays in
        (:data:`loopcal.calibration.parameters.NOMINAL`; mm and mm/V).
    max_tilt_deg : float, default MAX_TILT_DEG
        Largest tilt of a waypoint's output axis, degrees, > 0.
    max_twist_deg : float, default MAX_TWIST_DEG
        Largest twist of a waypoint about the plate's own axis, degrees, >= 0.

    Attributes
    ----------
    seed : int
        As given.
    waypoints : int
        As given.
    move_s : float
        As given, s.
    dwell_s : float
        As given, s.
    params : ndarray of float, shape (20,)
        As given.
    max_tilt_deg : float
        As given, degrees.
    max_twist_deg : float
        As given, degrees.
    orientations : ndarray of float, shape (waypoints, 3, 3)
        The waypoints' rotation matrices (plate frame in base frame), in loop order.

    Raises
    ------
    ValueError
        If ``waypoints`` is not an integer >= 2, ``move_s`` not a finite number > 0,
        ``dwell_s`` not a finite number >= 0, or a largest angle out of its range; the
        message names the parameter and the value.
    """

    name = "task"

    def __init__(
        self,
        seed: int = 0,
        *,
        waypoints: int = 5,
        move_s: float = 2.0,
        dwell_s: float = 0.5,
        params: np.ndarray = NOMINAL,
        max_tilt_deg: float = MAX_TILT_DEG,
        max_twist_deg: float = MAX_TWIST_DEG,
    ) -> None:
        if isinstance(waypoints, bool) or not isinstance(waypoints, numbers.Integral):
            raise ValueError(f"task loop: waypoints must be an integer, got {waypoints!r}")
        if waypoints < 2:
            raise ValueError(f"task loop: waypoints must be 2 or more, got {waypoints}")
        for what, value, least in (("move_s", move_s, None), ("dwell_s", dwell_s, 0.0),
                                   ("max_tilt_deg", max_tilt_deg, None),
                                   ("max_twist_deg", max_twist_deg, 0.0)):  # fmt: skip
            ok = isinstance(value, numbers.Real) and np.isfinite(value)
            ok = ok and (value >= least if least is not None else value > 0)
            if not ok:
                need = "0 or more" if least is not None else "more than 0"
                raise ValueError(f"task loop: {what} must be a finite number, {need}, got "
                                 f"{value!r}")  # fmt: skip
        if max_tilt_deg >= 90.0:
            raise ValueError(f"task loop: max_tilt_deg must be under 90, got {max_tilt_deg!r}")
        self.seed = seed
        self.waypoints = int(waypoints)
        self.move_s, self.dwell_s = float(move_s), float(dwell_s)
        self.params = np.asarray(params, dtype=float)
        self.max_tilt_deg, self.max_twist_deg = float(max_tilt_deg), float(max_twist_deg)
        self.orientations = self._draw()
        # one slerp through the loop's waypoints, back to the first: move i is the keyframe
        # interval [i, i + 1], its progress the minimum-jerk fraction of the move's time
        keys = Rotation.from_matrix(np.concatenate([self.orientations, self.orientations[:1]]))
        self._slerp = Slerp(np.arange(self.waypoints + 1, dtype=float), keys)

    @property
    def period_s(self) -> float:
        """One round of the loop, s: ``waypoints * (move_s + dwell_s)``."""
        return self.waypoints * (self.move_s + self.dwell_s)

    def _draw(self) -> np.ndarray:
        """The waypoints from the seed, each reachable and reachable from the one before
        (the last also back to the first), shape (waypoints, 3, 3)."""
        n = self.waypoints
        rng = np.random.default_rng(self.seed)
        phase = rng.uniform(-np.pi, np.pi)
        sector = 2.0 * np.pi / n
        out: list[np.ndarray] = []
        for i in range(n):  # a handful of waypoints, drawn once
            for attempt in range(2 * DRAWS):
                shrink = 1.0 - max(0, attempt - DRAWS + 1) / DRAWS  # 1, ..., 1, then to 0
                azimuth = phase + i * sector + rng.uniform(-0.25, 0.25) * sector
                tilt = np.radians(self.max_tilt_deg) * rng.uniform(0.6, 1.0) * shrink
                twist = (-1) ** i * np.radians(self.max_twist_deg) * rng.uniform(0.4, 1.0)
                R = from_euler_zyz([azimuth, tilt, twist * shrink - azimuth])[0]
                ends = [out[-1]] if out else []
                ends += [out[0]] if i == n - 1 else []
                if self._reachable(R, ends):
                    out.append(R)
                    break
            else:  # pragma: no cover - shrunk to home, which every loop reaches
                out.append(np.eye(3))
        return np.stack(out)

    def _reachable(self, R: np.ndarray, ends: list[np.ndarray]) -> bool:
        """Whether ``R`` (3, 3) is in the workspace with a margin, and the shortest rotation
        from it to each of ``ends`` stays in it."""
        if not reachable(R[None], self.params, margin_mm=1.5 * NEAR_SINGULAR_MM)[0]:
            return False
        for end in ends:
            slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([R, end])))
            path = slerp(np.linspace(0.0, 1.0, PATH_CHECKS)).as_matrix()
            if not reachable(path, self.params, margin_mm=NEAR_SINGULAR_MM).all():
                return False
        return True

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """The plate's orientation at times ``t``.

        Parameters
        ----------
        t : array_like of float, shape (k,)
            Source times, s, any order (a scalar is one time); before 0 the plate is at
            waypoint 0.

        Returns
        -------
        ndarray of float, shape (k, 3, 3)
            Rotation matrices: a waypoint during its dwell, the minimum-jerk slerp between
            two consecutive waypoints during a move; the same at ``t`` and at ``t`` plus
            any whole number of periods.

        Raises
        ------
        ValueError
            If a time is not finite.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float)).ravel()
        if not np.isfinite(t).all():
            raise ValueError("task loop: times must be finite")
        leg = self.move_s + self.dwell_s  # a dwell at waypoint i, then the move to i + 1
        phase = np.mod(np.maximum(t, 0.0), self.period_s)
        i = np.minimum(np.floor(phase / leg), self.waypoints - 1)
        tau = (phase - i * leg - self.dwell_s) / self.move_s  # <= 0 in the dwell
        # the polynomial can round a hair past 1 just before the end
        progress = np.clip(min_jerk(tau), 0.0, 1.0)
        out = self._slerp(i + progress).as_matrix().reshape(-1, 3, 3)
        # at a waypoint (a dwell, a move's ends) exactly the waypoint, whichever leg the
        # time's rounding put it in
        at, to = progress == 0.0, progress == 1.0
        out[at] = self.orientations[i[at].astype(int)]
        out[to] = self.orientations[(i[to].astype(int) + 1) % self.waypoints]
        return out

    def describe(self) -> dict:
        """``{"name": "task", "seed", "waypoints", "move_s", "dwell_s", "period_s", ...}``.

        Returns
        -------
        dict
            The name, the settings (s, degrees) and the waypoints' Z-Y-Z Euler angles
            (``"euler_deg"``, one triple per waypoint, degrees).
        """
        euler = np.degrees(euler_zyz(self.orientations))
        return {
            "name": self.name,
            "seed": self.seed,
            "waypoints": self.waypoints,
            "move_s": self.move_s,
            "dwell_s": self.dwell_s,
            "period_s": self.period_s,
            "max_tilt_deg": self.max_tilt_deg,
            "max_twist_deg": self.max_twist_deg,
            "euler_deg": [[round(float(a), 6) for a in e] for e in euler],
        }
