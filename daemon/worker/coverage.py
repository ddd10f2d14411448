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

from collections.abc import Callable
from functools import cache

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


def _reach(R: np.ndarray, params: np.ndarray) -> np.ndarray:
    """(4,) the largest tilt toward each sensor of rotations R (:func:`coverage`)."""
    tilt, az = np.degrees(output_axis_angles(R))
    A = base_points(params)
    reach = np.zeros(4)
    for i in range(4):
        a = np.degrees(np.arctan2(A[i, 1], A[i, 0]))
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


def coverage_advice(volts: np.ndarray, params: np.ndarray, *, still: bool = True) -> str:
    """Which way the technician should tilt the plate next, from where the poses went.

    The plate's output axis (its z axis) of each pose, by forward kinematics: for each
    sensor, the largest tilt reached towards that sensor's base point (within 45 deg of its
    azimuth, :func:`coverage`). The sensor reached least is where to go.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The poses' mean readings, V.
    params : ndarray of float, shape (20,)
        The parameters to turn them into poses with.
    still : bool, default True
        The fit uses still poses (the advice asks to hold each position); False: every
        scan, moving or still (it asks for motion).

    Returns
    -------
    str
        The advice: tilt further toward the sensor reached least (while it is under
        :data:`GOOD_TILT_DEG`, 25 deg), else twist the plate about its own axis the way it
        was twisted least (while under :data:`GOOD_TWIST_DEG`, 30 deg,
        :func:`twist_coverage`), else record more positions spread over the workspace,
        tilted and twisted; with no poses, move the plate through its whole range.
    """
    if len(volts) == 0:
        hold = ", holding each position still for a second" if still else ""
        return "move the plate by hand through its whole range, tilting and twisting it" + hold
    reach, twist = reach_and_twist(volts, params)
    return advice_from_coverage(reach, twist, still=still)


def advice_from_coverage(reach: np.ndarray, twist: np.ndarray, *, still: bool = True) -> str:
    """:func:`coverage_advice` from coverages already found (:func:`reach_and_twist`).

    Parameters
    ----------
    reach : ndarray of float, shape (4,)
        The largest tilt reached toward each sensor, deg.
    twist : ndarray of float, shape (2,)
        The largest twist reached clockwise and counter-clockwise seen from above, deg.
    still : bool, default True
        As for :func:`coverage_advice`.

    Returns
    -------
    str
        The advice, as :func:`coverage_advice` gives it.
    """
    hold = ", holding each position still for a second" if still else ""
    worst = int(np.argmin(reach))
    if reach[worst] >= GOOD_TILT_DEG:
        least = int(np.argmin(twist))
        if twist[least] < GOOD_TWIST_DEG:
            way = ("clockwise", "counter-clockwise")[least]
            return (
                f"twist the plate about its own axis, {way} seen from above (the "
                f"{'poses' if still else 'scans'} reach only {twist[least]:.0f} deg that way; "
                f"aim for {GOOD_TWIST_DEG:.0f} deg or more){hold}"
            )
        if still:
            return "record more still positions spread over the whole workspace, tilted and twisted"
        return "keep moving the plate through the whole workspace, tilting and twisting it"
    return (
        f"tilt the plate further toward sensor {worst + 1} (the {'poses' if still else 'scans'}"
        f" reach only {reach[worst]:.0f} deg that way; aim for {GOOD_TILT_DEG:.0f} deg or "
        f"more){hold}"
    )


def lazy_coverage_advice(
    volts: np.ndarray, params: np.ndarray, *, still: bool = True
) -> Callable[[], str]:
    """:func:`coverage_advice`, made on the first call and only then.

    Forward kinematics of every pose (a day's 30,000 of them) is paid for only when a gate
    fails and needs it.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The poses' mean readings, V.
    params : ndarray of float, shape (20,)
        The parameters to turn them into poses with.

    Returns
    -------
    callable
        ``advice() -> str``, computing the advice once and then returning it again: an
        :data:`~loopcal.daemon.worker.gates.Advice` for the gates
        (:func:`~loopcal.daemon.worker.gates.condition_gate`,
        :func:`~loopcal.daemon.worker.gates.min_singular_gate`,
        :func:`~loopcal.daemon.worker.gates.precision_gate`).
    """
    return cache(lambda: coverage_advice(volts, params, still=still))
