"""How the simulated plate moves: orientation as a function of device time.

A scenario maps times ``t`` (seconds since the module's first power-on, shape (k,)) to plate
rotations (k, 3, 3), deterministically for its seed, whatever order it is asked in.

- :class:`HandMoves`: a technician moving the plate by hand: smooth minimum-jerk moves
  between random reachable orientations, with pauses (the still segments calibration poses
  come from).
- :class:`Static`: the plate held still.
- :class:`Sweep`: the output axis circling at a fixed tilt while the plate swivels.
- :class:`~loopcal.simulator.task.TaskLoop` (its own module): the controller driving the
  plate round a fixed loop of waypoints, for ever.

The base class :class:`~loopcal.simulator.motion.Scenario` and :func:`min_jerk` are
:mod:`loopcal.simulator.motion`'s, imported here as before.
"""

from __future__ import annotations

import bisect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TypedDict, Unpack

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from loopcal.calibration.errors import InputError
from loopcal.calibration.kinematics import base_points, from_euler_zyz, tilt_swivel
from loopcal.calibration.parameters import NOMINAL
from loopcal.calibration.simulate import NEAR_SINGULAR_MM, reachable, sample_workspace

from .choices import SCENARIO_NAMES
from .motion import Scenario, min_jerk
from .task import TaskLoop


class Static(Scenario):
    """The plate held at one orientation.

    Parameters
    ----------
    euler_deg : tuple of 3 float, default (0.0, 0.0, 0.0)
        Intrinsic Z-Y-Z Euler angles of the orientation, degrees (the default is home).

    Attributes
    ----------
    euler_deg : tuple of 3 float
        As given.
    """

    name = "static"

    def __init__(self, euler_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        self.euler_deg = tuple(float(a) for a in euler_deg)
        self._R = from_euler_zyz(np.radians(self.euler_deg))[0]

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """The held orientation, once per time.

        Parameters
        ----------
        t : array_like of float, shape (k,)
            Source times, s (only their number matters).

        Returns
        -------
        ndarray of float, shape (k, 3, 3)
            The same rotation k times.
        """
        return np.broadcast_to(self._R, (np.size(t), 3, 3)).copy()

    def describe(self) -> dict:
        """``{"name": "static", "euler_deg": [...]}``.

        Returns
        -------
        dict
            The name and the Euler angles, degrees.
        """
        return {"name": self.name, "euler_deg": list(self.euler_deg)}


class Sweep(Scenario):
    """The output axis circles at a fixed tilt while the plate swivels.

    The output axis circles at ``tilt_deg`` once per ``period_s`` while the plate swivels
    by ``+-swivel_deg`` (sinusoidally, once per two periods).

    Parameters
    ----------
    period_s : float, default 20.0
        Time of one circle of the output axis, s, > 0.
    tilt_deg : float, default 20.0
        Tilt of the output axis from the base's z axis, degrees.
    swivel_deg : float, default 20.0
        Amplitude of the swivel about the output axis, degrees.

    Attributes
    ----------
    period_s : float
        As given.
    tilt_deg : float
        As given.
    swivel_deg : float
        As given.

    Raises
    ------
    ValueError
        If ``period_s`` is not positive, or the sweep leaves the nominal mechanism's
        reachable workspace (checked at 400 instants over two periods, with the
        near-singular margin).
    """

    name = "sweep"

    def __init__(
        self, period_s: float = 20.0, tilt_deg: float = 20.0, swivel_deg: float = 20.0
    ) -> None:
        if period_s <= 0:
            raise ValueError("sweep period must be positive")
        self.period_s, self.tilt_deg, self.swivel_deg = float(period_s), tilt_deg, swivel_deg
        check = self.rotation(np.linspace(0.0, 2 * period_s, 400))
        if not reachable(check, NOMINAL, margin_mm=NEAR_SINGULAR_MM).all():
            raise ValueError(
                f"a sweep at {tilt_deg} deg tilt and +-{swivel_deg} deg swivel leaves the "
                "reachable workspace; choose a smaller tilt or swivel"
            )

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """The plate's orientation at times ``t``.

        Parameters
        ----------
        t : array_like of float, shape (k,)
            Source times, s.

        Returns
        -------
        ndarray of float, shape (k, 3, 3)
            Z-Y-Z Euler angles ``(alpha, tilt, swivel - alpha)`` with
            ``alpha = 2 pi t / period_s`` and ``swivel = swivel_deg sin(pi t / period_s)``.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        alpha = 2 * np.pi * t / self.period_s
        swivel = np.radians(self.swivel_deg) * np.sin(np.pi * t / self.period_s)
        beta = np.full_like(t, np.radians(self.tilt_deg))
        return from_euler_zyz(np.column_stack([alpha, beta, swivel - alpha]))

    def describe(self) -> dict:
        """``{"name": "sweep", "period_s", "tilt_deg", "swivel_deg"}``.

        Returns
        -------
        dict
            The name and the settings (s, degrees).
        """
        return {
            "name": self.name,
            "period_s": self.period_s,
            "tilt_deg": self.tilt_deg,
            "swivel_deg": self.swivel_deg,
        }


@dataclass(frozen=True)
class _Segment:
    start: float
    end: float
    slerp: Slerp | None  # None: a pause at `hold`
    hold: Rotation


#: orientations drawn for a twisting move of :class:`HandMoves`, the most twisted one taken
TWIST_CANDIDATES = 8
#: source time, s, of motion :class:`HandMoves` keeps before the earliest time last asked for
HISTORY_S = 600.0
#: segments forgotten at a time (beyond :data:`HISTORY_S`)
FORGET_BATCH = 512


class HandStyle(TypedDict, total=False):
    """How a hand moves the plate, and in which mechanism: :class:`HandMoves`' keywords that
    :class:`GuidedHand` passes on (their defaults are :class:`HandMoves`').

    Attributes
    ----------
    pause_s : tuple of 2 float
        (min, max) of each pause's duration, s.
    speed_deg_s : tuple of 2 float
        (min, max) of each move's average angular speed, degrees per second.
    params : ndarray of float, shape (20,)
        The mechanism whose workspace the moves stay in (mm, mm/V).
    """

    pause_s: tuple[float, float]
    speed_deg_s: tuple[float, float]
    params: np.ndarray


class HandMoves(Scenario):
    """A technician moving the plate by hand.

    From home, the plate pauses (``pause_s`` range), then moves along the shortest rotation to
    a random reachable orientation with a minimum-jerk profile at a peak-to-average speed
    typical of a hand (``speed_deg_s`` range of average angular speeds), pauses, and so on.
    Every orientation on a move stays inside the reachable workspace with a margin from
    singular configurations. Segments are generated on demand from ``seed``.

    Parameters
    ----------
    seed : int, default 0
        Seed of the pauses, the targets and the speeds.
    pause_s : tuple of 2 float, default (1.0, 3.0)
        (min, max) of each pause's duration, s (drawn uniformly).
    speed_deg_s : tuple of 2 float, default (15.0, 40.0)
        (min, max) of each move's average angular speed, degrees per second (drawn
        uniformly; a move lasts at least 0.5 s).
    params : ndarray of float, shape (20,), default NOMINAL
        The mechanism whose workspace the moves stay in
        (:data:`loopcal.calibration.parameters.NOMINAL`; mm and mm/V).
    twist_every : int, default 0
        Every ``twist_every``-th move goes to the most twisted (largest swivel either way) of
        :data:`TWIST_CANDIDATES` reachable orientations: a technician who also twists the
        plate about its own axis, as the live guidance asks (0: never; every target drawn
        uniformly). 0 draws exactly the motion it drew before the option existed.

    Attributes
    ----------
    seed : int
        As given.
    pause_s : tuple of 2 float
        As given.
    speed_deg_s : tuple of 2 float
        As given.
    params : ndarray of float, shape (20,)
        As given.
    twist_every : int
        As given.

    Notes
    -----
    The moves are drawn in time order as far as they are asked for: the same seed gives
    the same motion whatever order the times are asked in. A source streaming forward (the
    emulator, for months) keeps the moves of the last :data:`HISTORY_S` only, so its memory
    and the cost of each call stay bounded; a time before those is drawn again from the seed.
    """

    name = "hand"

    def __init__(
        self,
        seed: int = 0,
        *,
        pause_s: tuple[float, float] = (1.0, 3.0),
        speed_deg_s: tuple[float, float] = (15.0, 40.0),
        params: np.ndarray = NOMINAL,
        twist_every: int = 0,
    ) -> None:
        if twist_every < 0:
            raise InputError(f"twist_every must be 0 or more moves, got {twist_every}")
        self.seed = seed
        self.pause_s = pause_s
        self.speed_deg_s = speed_deg_s
        self.params = np.asarray(params, dtype=float)
        self.twist_every = int(twist_every)
        self._restart()

    def _restart(self) -> None:
        """Back to the first pause, the draws from ``seed`` again."""
        self._moves = 0
        self._rng = np.random.default_rng(self.seed)
        self._segments: list[_Segment] = []
        self._starts: list[float] = []
        self._starts_array: np.ndarray | None = None
        self._forgotten = False  # segments before the first kept one were dropped
        self._append(_Segment(0.0, self._pause(), None, Rotation.identity()))

    def _pause(self) -> float:
        return float(self._rng.uniform(*self.pause_s))

    def _append(self, seg: _Segment) -> None:
        self._segments.append(seg)
        self._starts.append(seg.start)
        self._starts_array = None

    def _cover(self, t_min: float, t_max: float) -> np.ndarray:
        """Have the segments from ``t_min`` to ``t_max`` (s) at hand; forget those that
        ended :data:`HISTORY_S` before ``t_min`` (a source streaming for months keeps a
        bounded history), drawing them again from the seed if an earlier time is asked for.
        Returns the kept segments' start times."""
        if self._forgotten and t_min < self._starts[0]:
            self._restart()
        while self._segments[-1].end <= t_max:
            self._extend()
        if self._starts_array is None:
            self._starts_array = np.array(self._starts)
        old = int(np.searchsorted(self._starts_array, t_min - HISTORY_S, side="right")) - 1
        if old >= FORGET_BATCH:  # in batches: the list copy is paid once per batch
            del self._segments[:old], self._starts[:old]
            self._starts_array = self._starts_array[old:]
            self._forgotten = True
        return self._starts_array

    def _extend(self) -> None:
        last = self._segments[-1]
        here = last.hold
        self._moves += 1
        target, slerp = self._target(here, last.end)
        angle = np.degrees((here.inv() * target).magnitude())
        duration = max(0.5, angle / self._rng.uniform(*self.speed_deg_s))
        t0 = last.end
        self._append(_Segment(t0, t0 + duration, slerp, target))
        self._append(_Segment(t0 + duration, t0 + duration + self._pause(), None, target))

    def _path(self, here: Rotation, target: Rotation) -> Slerp | None:
        """The shortest rotation from ``here`` to ``target``, if it stays in the workspace."""
        slerp = Slerp([0.0, 1.0], Rotation.concatenate([here, target]))
        path = slerp(np.linspace(0.0, 1.0, 24)).as_matrix()
        return slerp if reachable(path, self.params, margin_mm=NEAR_SINGULAR_MM).all() else None

    def _target(self, here: Rotation, t0: float) -> tuple[Rotation, Slerp]:
        """The next move's target from ``here`` (the move starts at ``t0``, s) and its path:
        a random reachable orientation, every ``twist_every``-th move the most twisted of
        :data:`TWIST_CANDIDATES`."""
        twist = self.twist_every > 0 and self._moves % self.twist_every == 0
        for _ in range(100):
            drawn = sample_workspace(TWIST_CANDIDATES if twist else 1, self._rng, self.params,
                                     margin_mm=1.5 * NEAR_SINGULAR_MM)  # fmt: skip
            if twist:
                drawn = drawn[np.argmax(np.abs(tilt_swivel(drawn)[1]))][None]
            target = Rotation.from_matrix(drawn[0])
            slerp = self._path(here, target)
            if slerp is not None:
                break
        else:  # pragma: no cover - the workspace is connected around home
            target = Rotation.identity()
            slerp = Slerp([0.0, 1.0], Rotation.concatenate([here, target]))
        return target, slerp

    def segments_until(self, t: float) -> list[tuple[float, float, bool]]:
        """Every move and pause that starts by time ``t``: which stretches are still.

        Parameters
        ----------
        t : float
            Source time, s.

        Returns
        -------
        list of tuple (float, float, bool)
            ``(start, end, moving)`` of each segment starting at or before ``t``, in
            order, times in s; ``moving`` False for a pause.
        """
        self._cover(0.0, t)
        return [(s.start, s.end, s.slerp is not None) for s in self._segments if s.start <= t]

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """The plate's orientation at times ``t``.

        Parameters
        ----------
        t : array_like of float, shape (k,)
            Source times, s, any order.

        Returns
        -------
        ndarray of float, shape (k, 3, 3)
            Rotation matrices: the held orientation in a pause, the minimum-jerk slerp
            between two orientations in a move.
        """
        t = np.atleast_1d(np.asarray(t, dtype=float))
        starts = self._cover(float(t.min()), float(t.max()))
        out = np.empty((t.size, 3, 3))
        # vectorised per segment: one slerp call for all the times in a move
        seg_of = np.maximum(np.searchsorted(starts, t, side="right") - 1, 0)
        order = np.argsort(seg_of, kind="stable")
        bounds = np.flatnonzero(np.diff(seg_of[order])) + 1
        for idx in np.split(order, bounds):
            if not idx.size:
                continue
            seg = self._segments[seg_of[idx[0]]]
            if seg.slerp is None:
                out[idx] = seg.hold.as_matrix()
            else:
                tau = (t[idx] - seg.start) / (seg.end - seg.start)
                # the polynomial can round a hair past 1 just before the end
                out[idx] = seg.slerp(np.clip(min_jerk(tau), 0.0, 1.0)).as_matrix()
        return out

    def describe(self) -> dict:
        """``{"name": "hand", "seed", "pause_s", "speed_deg_s"}``.

        Returns
        -------
        dict
            The name and the settings (s, degrees per second).
        """
        return {
            "name": self.name,
            "seed": self.seed,
            "pause_s": list(self.pause_s),
            "speed_deg_s": list(self.speed_deg_s),
        }


#: what :meth:`GuidedHand.steer` understands: the ``kind`` of the live guidance's advice
#: (``"advice"`` in ``loopcal record --until-enough --json``)
ADVICE_KINDS = ("tilt", "twist", "anywhere", "enough", "other")


def _instruction(advice: Mapping[str, Any] | None) -> tuple | None:
    """What an advice asks for, whatever it says of the progress so far (``reached_deg``):
    a technician notices a new instruction, not a number that moved."""
    if advice is None:
        return None
    return advice["kind"], advice.get("sensor"), advice.get("way")


class GuidedHand(HandMoves):
    """A technician who does what the live guidance shows, as a person does it.

    The plate moves and pauses as with :class:`HandMoves` (minimum-jerk moves, pauses of
    ``pause_s``, speeds of ``speed_deg_s``, every orientation reachable), but each move goes
    where the advice last given before it starts asks (:meth:`steer`, once a second in a
    closed loop; the advice is the guidance's structured advice as JSON):

    - ``"tilt"``: toward ``azimuth_deg`` (else the side of ``sensor``), the plate's axis
      tilted to ``aim_deg`` plus up to ``beyond_deg`` (uniform: "aim for 25 deg or more"),
      with a natural swivel of standard deviation ``side_deg``;
    - ``"twist"``: about the plate's own axis the ``way`` asked (clockwise seen from above
      is a negative swivel) to ``aim_deg`` plus up to ``beyond_deg``, tilted up to
      ``side_deg`` in any direction;
    - ``"anywhere"``, ``"other"``, or no advice yet: as :class:`HandMoves` does, tilting and
      twisting (the most twisted of :data:`TWIST_CANDIDATES` every ``twist_every``-th move);
    - ``"enough"``: the plate held where it is.

    A person's imprecision: the angle reached is off by ``aim_sd_deg`` (standard deviation)
    and the direction by ``azimuth_sd_deg``; after the advice changes, each move has the
    chance ``late`` of still following the one before (a move or two late); each tilt or
    twist has the chance ``wrong`` of going the wrong way (the opposite side, the other
    twist). A target beyond the mechanism's reach is approached as far as it goes (the tilt
    and twist scaled down in steps of 5 % until the orientation and the way there are
    reachable).

    Parameters
    ----------
    seed : int, default 0
        Seed of the pauses, speeds, targets and imprecision.
    twist_every : int, default 2
        For ``"anywhere"`` moves: every so many moves the most twisted of eight (0: never).
    aim_sd_deg : float, default 5.0
        Standard deviation of the tilt or twist reached about the one aimed for, degrees.
    azimuth_sd_deg : float, default 10.0
        Standard deviation of the direction of a tilt about the one asked for, degrees.
    beyond_deg : float, default 10.0
        How far past ``aim_deg`` a technician goes at most (uniform from 0), degrees.
    side_deg : float, default 10.0
        Tilting: the standard deviation of the unintended swivel; twisting: the largest
        unintended tilt; degrees.
    late : float, default 0.25
        Chance, per move, of still following the advice before it changed, 0..1.
    wrong : float, default 0.15
        Chance, per tilt or twist, of going the wrong way, 0..1.
    **hand
        ``pause_s`` (s), ``speed_deg_s`` (degrees per second) and ``params`` (shape (20,),
        mm and mm/V): the hand's and the mechanism's, as :class:`HandMoves` takes them
        (:class:`HandStyle`), with its defaults.

    Attributes
    ----------
    aim_sd_deg, azimuth_sd_deg, beyond_deg, side_deg, late, wrong : float
        As given (and those of :class:`HandMoves`).

    Raises
    ------
    InputError
        If a chance is outside 0..1, an angle negative, or ``twist_every`` negative.

    Notes
    -----
    The motion is a function of the seed and of the advice given and when: a move starting
    at time s follows the latest advice given for a time at or before s. Advice can only be
    given for a time after every move already drawn has started (:meth:`steer`), so the
    same seed and advice give the same motion whatever order the times are asked in.
    """

    name = "guided"

    def __init__(
        self,
        seed: int = 0,
        *,
        twist_every: int = 2,
        aim_sd_deg: float = 5.0,
        azimuth_sd_deg: float = 10.0,
        beyond_deg: float = 10.0,
        side_deg: float = 10.0,
        late: float = 0.25,
        wrong: float = 0.15,
        **hand: Unpack[HandStyle],
    ) -> None:
        for name, chance in (("late", late), ("wrong", wrong)):
            if not 0.0 <= chance <= 1.0:
                raise InputError(f"{name} must be a chance from 0 to 1, got {chance}")
        angles = {"aim_sd_deg": aim_sd_deg, "azimuth_sd_deg": azimuth_sd_deg,
                  "beyond_deg": beyond_deg, "side_deg": side_deg}  # fmt: skip
        for name, deg in angles.items():
            if not deg >= 0.0:
                raise InputError(f"{name} must be 0 or more degrees, got {deg}")
        self.aim_sd_deg, self.azimuth_sd_deg = float(aim_sd_deg), float(azimuth_sd_deg)
        self.beyond_deg, self.side_deg = float(beyond_deg), float(side_deg)
        self.late, self.wrong = float(late), float(wrong)
        self._steers: list[tuple[float, dict[str, Any] | None]] = []
        super().__init__(seed, twist_every=twist_every, **hand)

    def _restart(self) -> None:
        super()._restart()
        self._followed: dict[str, Any] | None = None  # the advice the last move followed
        self._drawn_until = -np.inf  # the start of the last move drawn, s

    def steer(self, advice: Mapping[str, Any] | None, at_s: float) -> None:
        """Show the technician the advice from time ``at_s`` on.

        Parameters
        ----------
        advice : mapping or None
            The live guidance's structured advice as JSON (``"advice"`` of an update of
            ``loopcal record --until-enough --json``): ``"kind"`` one of
            :data:`ADVICE_KINDS`; a ``"tilt"`` with ``"aim_deg"`` and ``"azimuth_deg"`` or
            ``"sensor"`` (1..4), a ``"twist"`` with ``"aim_deg"`` and ``"way"``
            (``"clockwise"`` or ``"counter-clockwise"`` seen from above). None: no advice.
        at_s : float
            Source time from which it is shown, s: the moves starting then or later follow
            it (until the next advice).

        Raises
        ------
        ValueError
            If ``at_s`` is not after the start of every move already drawn (the plate's
            motion up to then is decided) or before the last advice's time, or the advice
            lacks what its kind needs.
        """
        at_s = float(at_s)
        decided = max(self._drawn_until, self._steers[-1][0] if self._steers else -np.inf)
        if at_s <= self._drawn_until or at_s < decided:
            raise ValueError(f"advice for {at_s:g} s comes too late: the motion up to "
                             f"{decided:g} s is decided")  # fmt: skip
        self._steers.append((at_s, None if advice is None else self._checked(advice)))

    def _checked(self, advice: Mapping[str, Any]) -> dict[str, Any]:
        """A copy of ``advice`` with the direction of a tilt (``azimuth_deg``), or ValueError
        if it lacks what its kind needs."""
        out = dict(advice)
        kind = out.get("kind")
        need = {"tilt": ("aim_deg",), "twist": ("aim_deg", "way")}.get(kind, ())
        if kind not in ADVICE_KINDS or any(out.get(k) is None for k in need):
            raise ValueError(f"advice {out!r}: a kind of {', '.join(ADVICE_KINDS)}, with "
                             "aim_deg for a tilt or twist, and its way for a twist")  # fmt: skip
        if kind == "twist" and out["way"] not in ("clockwise", "counter-clockwise"):
            raise ValueError(f"advice {out!r}: the way clockwise or counter-clockwise")
        if kind == "tilt" and out.get("azimuth_deg") is None:
            if out.get("sensor") not in (1, 2, 3, 4):
                raise ValueError(f"advice {out!r}: a tilt needs azimuth_deg or sensor 1..4")
            A = base_points(self.params)[out["sensor"] - 1]
            out["azimuth_deg"] = float(np.degrees(np.arctan2(A[1], A[0])))
        return out

    def _advice(self, t0: float) -> dict[str, Any] | None:
        """The advice a move starting at ``t0`` follows: the latest shown by then, or (a
        move late, by chance) the one the last move followed."""
        i = bisect.bisect_right([s for s, _ in self._steers], t0) - 1
        now = self._steers[i][1] if i >= 0 else None
        before = self._followed
        if before is not None and _instruction(now) != _instruction(before):
            if self._rng.random() < self.late:
                return before
        self._followed = now
        return now

    def _target(self, here: Rotation, t0: float) -> tuple[Rotation, Slerp]:
        self._drawn_until = t0
        advice = self._advice(t0)
        kind = advice["kind"] if advice is not None else None
        if kind == "enough":
            return here, Slerp([0.0, 1.0], Rotation.concatenate([here, here]))
        if advice is None or kind not in ("tilt", "twist"):
            return super()._target(here, t0)
        rng = self._rng
        wrong = rng.random() < self.wrong
        reach = max(0.0, advice["aim_deg"] + rng.uniform(0.0, self.beyond_deg)
                    + rng.normal(0.0, self.aim_sd_deg))  # fmt: skip
        if kind == "tilt":
            azimuth = advice["azimuth_deg"] + rng.normal(0.0, self.azimuth_sd_deg)
            azimuth += 180.0 if wrong else 0.0
            tilt, swivel = reach, rng.normal(0.0, self.side_deg)
        else:
            way = -1.0 if advice["way"] == "clockwise" else 1.0
            azimuth, tilt = rng.uniform(-180.0, 180.0), rng.uniform(0.0, self.side_deg)
            swivel = -way * reach if wrong else way * reach
        return self._toward(here, azimuth, tilt, swivel)

    def _toward(self, here: Rotation, azimuth: float, tilt: float, swivel: float):
        """As far toward (azimuth, tilt, swivel), degrees, as the mechanism goes from here."""
        scale = np.linspace(1.0, 0.0, 21)
        a = np.radians(azimuth)
        R = from_euler_zyz(np.column_stack([np.full(scale.size, a), np.radians(tilt) * scale,
                                            np.radians(swivel) * scale - a]))  # fmt: skip
        for Rk in R[reachable(R, self.params, margin_mm=1.5 * NEAR_SINGULAR_MM)]:
            target = Rotation.from_matrix(Rk)
            slerp = self._path(here, target)
            if slerp is not None:
                return target, slerp
        target = Rotation.identity()  # home: the workspace is connected around it
        return target, Slerp([0.0, 1.0], Rotation.concatenate([here, target]))

    def describe(self) -> dict:
        """``{"name": "guided", "seed", "pause_s", "speed_deg_s", ...}``.

        Returns
        -------
        dict
            The name and the settings (s, degrees per second, degrees, chances).
        """
        return {**super().describe(), "twist_every": self.twist_every,
                "aim_sd_deg": self.aim_sd_deg, "azimuth_sd_deg": self.azimuth_sd_deg,
                "beyond_deg": self.beyond_deg, "side_deg": self.side_deg,
                "late": self.late, "wrong": self.wrong}  # fmt: skip


#: the scenarios by name, as ``loopcal simulate --scenario NAME`` offers them (the names:
#: :data:`~loopcal.simulator.choices.SCENARIO_NAMES`, which its ``--help`` reads)
SCENARIOS = dict(zip(SCENARIO_NAMES, (HandMoves, Static, Sweep, TaskLoop), strict=True))


def scenario_named(
    name: str,
    *,
    seed: int = 0,
    params: np.ndarray = NOMINAL,
    pause_s: tuple[float, float] = (1.0, 3.0),
    twist_every: int = 0,
    waypoints: int = 5,
    move_s: float = 2.0,
    dwell_s: float = 0.5,
) -> Scenario:
    """The scenario ``loopcal simulate --scenario NAME`` serves.

    Parameters
    ----------
    name : str
        ``"hand"`` (:class:`HandMoves`), ``"static"`` (:class:`Static`, held at home),
        ``"sweep"`` (:class:`Sweep` with its defaults) or ``"task"``
        (:class:`~loopcal.simulator.task.TaskLoop`).
    seed : int, default 0
        With "hand": the seed of the moves; with "task": the seed of the waypoints.
    params : ndarray of float, shape (20,), default NOMINAL
        With "hand" and "task": the mechanism whose workspace the moves stay in.
    pause_s : tuple of 2 float, default (1.0, 3.0)
        With "hand": (min, max) of each still pause, s.
    twist_every : int, default 0
        With "hand": every so many moves twist the plate about its own axis (0: never).
    waypoints : int, default 5
        With "task": the number of waypoints of the loop, >= 2.
    move_s : float, default 2.0
        With "task": each move between consecutive waypoints, s, > 0.
    dwell_s : float, default 0.5
        With "task": the dwell at each waypoint, s, >= 0.

    Returns
    -------
    Scenario
        A new scenario; each ignores the settings of the others ("static" and "sweep"
        all of them).

    Raises
    ------
    ValueError
        If ``name`` is not one of :data:`SCENARIOS`, or the task loop's settings are
        refused (:class:`~loopcal.simulator.task.TaskLoop`).
    """
    if name not in SCENARIOS:
        raise ValueError(f"scenario {name!r}: one of {', '.join(SCENARIOS)}")
    if name == "hand":
        return HandMoves(seed, params=params, pause_s=pause_s, twist_every=twist_every)
    if name == "task":
        return TaskLoop(seed, waypoints=waypoints, move_s=move_s, dwell_s=dwell_s, params=params)
    return SCENARIOS[name]()
