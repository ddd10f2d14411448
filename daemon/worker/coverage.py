"""Where the plate went, and where it should go next: the tilt and twist coverage of a
recording's poses (or usable scans) and the advice it gives the technician.

The plate's orientation of each pose comes from forward kinematics; its output axis says how
far it tilted toward each sensor (:func:`coverage`), its swivel how far it was twisted about
its own axis each way (:func:`twist_coverage`); both from one forward kinematics
(:func:`reach_and_twist`). The advice (:func:`coverage_advice`) asks for the sensor's side
reached least, then for the twist, then for more positions anywhere. The acceptance gates
(:mod:`loopcal.daemon.worker.gates`) take it as their advice when the motion was too little
or badly spread, made only if one fails (:func:`lazy_coverage_advice`), and the live guidance
(:mod:`loopcal.daemon.live.guidance`) shows it while the plate moves.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from loopcal.calibration.kinematics import (
    base_points,
    forward_kinematics,
    output_axis_angles,
    tilt_swivel,
    volts_to_lengths,
)

GOOD_TILT_DEG = 25.0  #: deg; the workspace allows 45, poses should reach this far every way
#: deg; how far to twist the plate about its own axis each way: the parameters' weakest
#: combination is learnt mostly from twisted positions (docs/calibration.md)
GOOD_TWIST_DEG = 30.0
POSITION_CELL_V = 1.0  #: V; scans count as distinct positions this far apart on a channel


def distinct_positions(volts: np.ndarray) -> int:
    """How many distinct positions scans passed through.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The scans' readings, V.

    Returns
    -------
    int
        The number of cells of :data:`POSITION_CELL_V` (1 V, about 4 mm of stroke) on
        every channel that the readings fall in; 0 for no scans. The ``poses`` gate of a
        fit on every scan counts these (:func:`loopcal.daemon.worker.gates.samples.scans_gate`).
    """
    if len(volts) == 0:
        return 0
    return len(np.unique(np.floor(volts / POSITION_CELL_V).astype(np.int64), axis=0))


def _rotations(volts: np.ndarray, params: np.ndarray) -> np.ndarray:
    """(j, 3, 3) plate rotations of the readings whose forward kinematics converged (readings
    a damaged channel made inconsistent are left out, not turned into a pose)."""
    fk = forward_kinematics(volts_to_lengths(volts, params), params)
    return fk.rotations[fk.converged & np.isfinite(fk.rotations).all(axis=(1, 2))]


def _twist(R: np.ndarray) -> np.ndarray:
    """(2,) the largest swivel of rotations R clockwise and counter-clockwise, deg."""
    if len(R) == 0:
        return np.zeros(2)
    swivel = np.degrees(tilt_swivel(R)[1])
    return np.array([max(0.0, -float(swivel.min())), max(0.0, float(swivel.max()))])


def sensor_azimuths(params: np.ndarray) -> np.ndarray:
    """Which way each sensor's side lies, seen from above.

    Parameters
    ----------
    params : ndarray of float, shape (20,)
        The mechanism's parameters (mm, mm/V).

    Returns
    -------
    ndarray of float, shape (4,)
        The azimuth of each sensor's base point A_i from the base's centre, degrees from the
        base's +x toward +y, in (-180, 180]: the direction "toward sensor i" of
        :func:`coverage` and of the advice.
    """
    A = base_points(params)
    return np.degrees(np.arctan2(A[:, 1], A[:, 0]))


def _reach(R: np.ndarray, params: np.ndarray) -> np.ndarray:
    """(4,) the largest tilt toward each sensor of rotations R (:func:`coverage`)."""
    tilt, az = np.degrees(output_axis_angles(R))
    reach = np.zeros(4)
    for i, a in enumerate(sensor_azimuths(params)):
        near = np.abs((az - a + 180) % 360 - 180) <= 45
        reach[i] = float(tilt[near].max()) if near.any() else 0.0
    return reach


def reach_and_twist(volts: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`coverage` and :func:`twist_coverage` of the same readings, from one forward
    kinematics.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The poses' readings, V.
    params : ndarray of float, shape (20,)
        The parameters to turn them into poses with.

    Returns
    -------
    reach : ndarray of float, shape (4,)
        The largest tilt toward each sensor, degrees (:func:`coverage`).
    twist : ndarray of float, shape (2,)
        The largest twist clockwise and counter-clockwise, degrees (:func:`twist_coverage`).
    """
    R = _rotations(volts, params) if len(volts) else np.zeros((0, 3, 3))
    return _reach(R, params), _twist(R)


def twist_coverage(volts: np.ndarray, params: np.ndarray) -> np.ndarray:
    """How far the poses twisted the plate about its own axis, each way.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The poses' readings, V.
    params : ndarray of float, shape (20,)
        The parameters to turn them into poses with (forward kinematics).

    Returns
    -------
    ndarray of float, shape (2,)
        The largest swivel (:func:`~loopcal.calibration.kinematics.tilt_swivel`) reached
        clockwise and counter-clockwise seen from above, degrees, both >= 0 (0 for no
        poses; readings whose forward kinematics does not converge count as none).
    """
    return reach_and_twist(volts, params)[1]


def coverage(volts: np.ndarray, params: np.ndarray) -> np.ndarray:
    """How far the poses tilted the plate toward each sensor.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The poses' mean readings, V.
    params : ndarray of float, shape (20,)
        The parameters to turn them into poses with (forward kinematics).

    Returns
    -------
    ndarray of float, shape (4,)
        For each sensor, the largest tilt of the plate's output axis, degrees, among the
        poses whose axis leans within 45 deg of the azimuth of that sensor's base point;
        0 where none does (and for no poses at all). Readings whose forward kinematics does
        not converge count as no pose.
    """
    return reach_and_twist(volts, params)[0]


#: what a :class:`NextMove` asks for
KINDS = ("tilt", "twist", "anywhere", "enough", "other")
#: the two ways to twist, as :func:`twist_coverage` orders them, seen from above
TWIST_WAYS = ("clockwise", "counter-clockwise")


@dataclass(frozen=True)
class NextMove:
    """What the technician should do next: the advice for a program to follow, beside its
    text for people (both made by one decision).

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`: ``"tilt"`` the plate toward ``sensor``'s side; ``"twist"`` it
        about its own axis the ``way`` given; ``"anywhere"``: move it through new positions,
        tilting and twisting (nothing is missing in particular, or it rested too long);
        ``"enough"``: the recording is complete, stop; ``"other"``: an instruction the
        fields do not describe (a failing gate's own advice, such as checking a sensor's
        wiring): read ``text``.
    text : str
        The advice in words, as the technician is shown it.
    sensor : int or None
        ``"tilt"``: the sensor (1..4) whose side to tilt toward; else None.
    azimuth_deg : float or None
        ``"tilt"``: the direction of that side, degrees from the base's +x toward +y
        (:func:`sensor_azimuths`); else None.
    aim_deg : float or None
        ``"tilt"``: the tilt of the plate's axis to reach that way (:data:`GOOD_TILT_DEG`);
        ``"twist"``: the swivel to reach that way (:data:`GOOD_TWIST_DEG`); degrees, else
        None.
    reached_deg : float or None
        ``"tilt"``, ``"twist"``: how far the poses reached that way so far, degrees; else
        None.
    way : str or None
        ``"twist"``: ``"clockwise"`` or ``"counter-clockwise"`` seen from above (one of
        :data:`TWIST_WAYS`); else None.
    """

    kind: str
    text: str
    sensor: int | None = None
    azimuth_deg: float | None = None
    aim_deg: float | None = None
    reached_deg: float | None = None
    way: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind {self.kind!r}: one of {', '.join(KINDS)}")

    def as_json(self) -> dict[str, Any]:
        """The advice as JSON-ready fields.

        Returns
        -------
        dict
            ``{"kind", "sensor", "azimuth_deg", "aim_deg", "reached_deg", "way"}`` (None
            where a field does not apply; angles rounded to 0.1 degree); the text is
            shown on its own (the guidance's ``instruction``).
        """

        def deg(x: float | None) -> float | None:
            return None if x is None else round(float(x), 1)

        return {"kind": self.kind, "sensor": self.sensor, "azimuth_deg": deg(self.azimuth_deg),
                "aim_deg": deg(self.aim_deg), "reached_deg": deg(self.reached_deg),
                "way": self.way}  # fmt: skip


def next_move(
    reach: np.ndarray, twist: np.ndarray, params: np.ndarray, *, still: bool = True
) -> NextMove:
    """Where the technician should take the plate next, from coverages already found
    (:func:`reach_and_twist`).

    Parameters
    ----------
    reach : ndarray of float, shape (4,)
        The largest tilt reached toward each sensor, deg.
    twist : ndarray of float, shape (2,)
        The largest twist reached clockwise and counter-clockwise seen from above, deg.
    params : ndarray of float, shape (20,)
        The mechanism's parameters: where each sensor's side lies (:func:`sensor_azimuths`).
    still : bool, default True
        The fit uses still poses (the advice asks to hold each position); False: every
        scan, moving or still (it asks for motion).

    Returns
    -------
    NextMove
        ``"tilt"`` toward the sensor reached least while it is under :data:`GOOD_TILT_DEG`,
        else ``"twist"`` the way twisted least while under :data:`GOOD_TWIST_DEG`, else
        ``"anywhere"``; its text as :func:`coverage_advice` gives it.
    """
    hold = ", holding each position still for a second" if still else ""
    what = "poses" if still else "scans"
    worst = int(np.argmin(reach))
    if reach[worst] < GOOD_TILT_DEG:
        return NextMove(
            "tilt",
            f"tilt the plate further toward sensor {worst + 1} (the {what} reach only "
            f"{reach[worst]:.0f} deg that way; aim for {GOOD_TILT_DEG:.0f} deg or more){hold}",
            sensor=worst + 1, azimuth_deg=float(sensor_azimuths(params)[worst]),
            aim_deg=GOOD_TILT_DEG, reached_deg=float(reach[worst]),
        )  # fmt: skip
    least = int(np.argmin(twist))
    if twist[least] < GOOD_TWIST_DEG:
        way = TWIST_WAYS[least]
        return NextMove(
            "twist",
            f"twist the plate about its own axis, {way} seen from above (the {what} reach "
            f"only {twist[least]:.0f} deg that way; aim for {GOOD_TWIST_DEG:.0f} deg or "
            f"more){hold}",
            aim_deg=GOOD_TWIST_DEG, reached_deg=float(twist[least]), way=way,
        )  # fmt: skip
    if still:
        return NextMove(
            "anywhere",
            "record more still positions spread over the whole workspace, tilted and twisted",
        )
    return NextMove(
        "anywhere", "keep moving the plate through the whole workspace, tilting and twisting it"
    )


def coverage_move(volts: np.ndarray, params: np.ndarray, *, still: bool = True) -> NextMove:
    """Where the technician should take the plate next, from where the poses went.

    The plate's output axis (its z axis) of each pose, by forward kinematics: for each
    sensor, the largest tilt reached towards that sensor's base point (within 45 deg of its
    azimuth, :func:`coverage`), and the largest twist each way (:func:`twist_coverage`);
    then :func:`next_move`.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The poses' mean readings, V.
    params : ndarray of float, shape (20,)
        The parameters to turn them into poses with.
    still : bool, default True
        As for :func:`next_move`.

    Returns
    -------
    NextMove
        As :func:`next_move` decides; with no poses, ``"anywhere"``: move the plate through
        its whole range.
    """
    if len(volts) == 0:
        hold = ", holding each position still for a second" if still else ""
        return NextMove("anywhere", "move the plate by hand through its whole range, tilting "
                        "and twisting it" + hold)  # fmt: skip
    reach, twist = reach_and_twist(volts, params)
    return next_move(reach, twist, params, still=still)


def coverage_advice(volts: np.ndarray, params: np.ndarray, *, still: bool = True) -> str:
    """Which way the technician should tilt the plate next, from where the poses went: the
    text of :func:`coverage_move`.

    Parameters
    ----------
    volts, params, still
        As for :func:`coverage_move`.

    Returns
    -------
    str
        The advice: tilt further toward the sensor reached least (while it is under
        :data:`GOOD_TILT_DEG`, 25 deg), else twist the plate about its own axis the way it
        was twisted least (while under :data:`GOOD_TWIST_DEG`, 30 deg,
        :func:`twist_coverage`), else record more positions spread over the workspace,
        tilted and twisted; with no poses, move the plate through its whole range.
    """
    return coverage_move(volts, params, still=still).text


def telling_move(params: np.ndarray, shifts: list[np.ndarray], *, still: bool = False) -> NextMove:
    """The move that best tells apart explanations of a change in the offsets.

    Each explanation (the offsets that moved, and by how much) predicts the loop-closure
    error of every position; where two explanations predict nearly the same errors over the
    motion seen, only a position where their predictions differ tells which is right. Among
    the plate tilted :data:`GOOD_TILT_DEG` toward each sensor and twisted
    :data:`GOOD_TWIST_DEG` each way about its own axis (the moves the guidance asks for),
    the one where the explanations' predictions differ most.

    Parameters
    ----------
    params : ndarray of float, shape (20,)
        The parameters in force.
    shifts : list of ndarray of float, shape (4,)
        Each explanation's shift of the four offsets, mm (at least two).
    still : bool, default False
        As for :func:`next_move`.

    Returns
    -------
    NextMove
        ``"tilt"`` toward a sensor or ``"twist"`` one way; ``"anywhere"`` when no such
        position is reachable.
    """
    from loopcal.calibration.closure import loop_closure
    from loopcal.calibration.kinematics import (
        from_euler_zyz,
        in_stroke,
        inverse_kinematics,
        lengths_to_volts,
    )

    params = np.asarray(params, dtype=float)
    az = np.radians(sensor_azimuths(params))
    tilt, twist = np.radians(GOOD_TILT_DEG), np.radians(GOOD_TWIST_DEG)
    angles = [[a, tilt, -a] for a in az] + [[0.0, 0.0, twist], [0.0, 0.0, -twist]]
    R = from_euler_zyz(np.array(angles))
    lengths = inverse_kinematics(R, params)
    ok = in_stroke(lengths, params).all(axis=1)
    volts = lengths_to_volts(lengths, params)
    h = loop_closure(volts, params, np.full(4, 0.04)).offset_pattern  # (6, 4), 1/mm
    D = np.array([a - b for i, a in enumerate(shifts) for b in shifts[i + 1 :]])  # (pairs, 4)
    score = np.where(ok, np.min(np.abs(h @ D.T), axis=1) if len(D) else 0.0, -1.0)
    best = int(np.argmax(score))
    hold = ", holding it there a few seconds" if still else ""
    if score[best] <= 0:
        return NextMove("anywhere", "move the plate through its whole range, tilting it toward "
                        "each sensor and twisting it both ways")
    if best < 4:
        return NextMove(
            "tilt", f"tilt the plate toward sensor {best + 1}, about {GOOD_TILT_DEG:.0f} deg"
            f"{hold}: there the explanations differ most",
            sensor=best + 1, azimuth_deg=float(np.degrees(az[best])), aim_deg=GOOD_TILT_DEG,
        )
    way = TWIST_WAYS[0] if best == 5 else TWIST_WAYS[1]
    return NextMove(
        "twist", f"twist the plate about its own axis, {way} seen from above, about "
        f"{GOOD_TWIST_DEG:.0f} deg{hold}: there the explanations differ most",
        aim_deg=GOOD_TWIST_DEG, way=way,
    )


class LazyAdvice:
    """:func:`coverage_move` of poses, made on first use and only then: the advice the
    acceptance gates give when the motion was too little or badly spread.

    Forward kinematics of every pose (a day's 30,000 of them) is paid for only when a gate
    fails and needs it, or the live guidance asks where to go; once made, both take the same
    decision.

    Parameters
    ----------
    volts, params, still
        As for :func:`coverage_move`.

    Attributes
    ----------
    still : bool
        As given.
    """

    def __init__(self, volts: np.ndarray, params: np.ndarray, *, still: bool = True) -> None:
        self._volts, self._params, self.still = volts, params, still
        self._move: NextMove | None = None

    @property
    def made(self) -> bool:
        """Whether the advice was made (a gate failed and asked, or :meth:`move` was called).

        Returns
        -------
        bool
        """
        return self._move is not None

    def move(self) -> NextMove:
        """The advice, made on the first call.

        Returns
        -------
        NextMove
            :func:`coverage_move` of the poses.
        """
        if self._move is None:
            self._move = coverage_move(self._volts, self._params, still=self.still)
        return self._move

    def __call__(self) -> str:
        """The advice's text (an :data:`~loopcal.daemon.worker.gates.Advice` for the gates).

        Returns
        -------
        str
            ``move().text``.
        """
        return self.move().text


#: :func:`coverage_advice`, made on the first call and only then: the gates' name for
#: :class:`LazyAdvice` (``lazy_coverage_advice(volts, params, still=still)``)
lazy_coverage_advice = LazyAdvice
