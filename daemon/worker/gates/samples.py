"""The motion gate: did the plate move enough, and every channel with it, for a fit; and
what the gates that follow from too little motion advise.

The ``poses`` gate, judged before any fit: for still poses (:func:`poses_gate`) and for a
fit on every scan (:func:`scans_gate`, in distinct positions:
:func:`~loopcal.daemon.worker.coverage.distinct_positions`). docs/calibration.md gives the
limits. When the motion passed it but did not tell the parameters apart (the ``condition``
or ``min_singular`` gate failed, or a change is within its own uncertainty), the other gates'
failures follow from that and advise what :func:`too_little_motion` says instead of their
own causes (a geometry, a gain).
"""

from __future__ import annotations

import numpy as np

from loopcal.calibration.parameters import GAIN_NOMINAL

from ..coverage import POSITION_CELL_V, distinct_positions
from .gate import Advice, Gate, advice_text

MIN_POSES = 30  #: still poses the ``poses`` gate needs at least
MIN_CHANNEL_RANGE_V = 0.5  #: V; a channel that moves less than this over all poses is stuck
BARELY_MOVED_V = 2.0  #: V; every channel within this over all poses, the plate barely moved


def _motion_failure(
    span: np.ndarray, n: int, over: str, move: str, unit: str = "poses"
) -> Gate | None:
    """The ``poses`` gate's failure when the plate barely moved or a channel never did
    (span: (4,) each channel's range, V; n: the gate's value; over: what the ranges are
    over, as text; move: the advice to move; unit: what the gate counts), else None.

    A channel that hardly moved while the others did is named stuck only if the plate
    went through :data:`MIN_POSES` positions: with fewer, too little motion is the first
    cause, and the advice moves the plate before it checks the sensor."""
    if span.max() < BARELY_MOVED_V:
        return Gate(
            "poses",
            False,
            n,
            f">= {MIN_POSES} {unit}, every channel moving",
            f"the plate barely moved: every channel stayed within {span.max():.2f} V "
            f"({span.max() * GAIN_NOMINAL:.1f} mm of stroke) over {over}",
            move,
        )
    stuck = [i + 1 for i in range(4) if span[i] < MIN_CHANNEL_RANGE_V]
    if stuck and len(stuck) < 4:
        names = ", ".join(f"sensor {i}" for i in stuck)
        ranges = ", ".join(f"{span[i - 1]:.3f} V" for i in stuck)
        if n < MIN_POSES:
            return Gate(
                "poses",
                False,
                n,
                f">= {MIN_POSES} {unit}, every channel moving",
                f"too little motion: only {n} {unit} over {over}, and {names} hardly moved "
                f"({ranges} range), which so little motion does not tell from a stuck sensor",
                f"{move}; if {names} still reads the same while the plate moves, check its "
                "LVDT core, cable and conditioner",
            )
        return Gate(
            "poses",
            False,
            n,
            f">= {MIN_POSES} {unit}, every channel moving",
            f"{names} read the same ({ranges} range) over {over} while the others moved: stuck "
            "or disconnected",
            f"check {names}: its LVDT core, cable and conditioner; then record again",
        )
    return None


def poses_gate(volts: np.ndarray) -> Gate:
    """Enough still poses, and no channel that never moved (stuck or disconnected).

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        Mean readings of every still pose found, V.

    Returns
    -------
    Gate
        ``"poses"``, its value the number of poses k.

    Notes
    -----
    Fails, in this order, when the plate barely moved (every channel's range over the
    poses under :data:`BARELY_MOVED_V`, 2 V, about 7.5 mm of stroke at the nominal gain),
    when some but not all channels moved less than :data:`MIN_CHANNEL_RANGE_V` (0.5 V:
    stuck or disconnected, named), and when there are fewer than :data:`MIN_POSES` (30)
    poses. The limits are docs/calibration.md's "poses" gate.
    """
    n = len(volts)
    if n:
        failed = _motion_failure(
            np.ptp(volts, axis=0), n, f"all {n} still poses",
            "move the plate by hand through its whole range (tilt it 25 deg or more "
            "toward each sensor), holding each position still for about a second",
        )  # fmt: skip
        if failed is not None:
            return failed
    if n < MIN_POSES:
        return Gate(
            "poses",
            False,
            n,
            f">= {MIN_POSES}",
            f"too little motion: only {n} still poses found in the recording",
            "move the plate to at least 40 positions, holding each still for about a second",
        )
    return Gate("poses", True, n, f">= {MIN_POSES}")


def scans_gate(volts: np.ndarray, seconds: float) -> Gate:
    """Enough motion in the usable scans, and no channel that never moved: the ``poses``
    gate of a fit on every scan.

    Parameters
    ----------
    volts : ndarray of float, shape (k, 4)
        The readings of the usable scans, V.
    seconds : float
        The time those scans span at the scan rate, s (for the text).

    Returns
    -------
    Gate
        ``"poses"``, its value the number of distinct positions
        (:func:`distinct_positions`).

    Notes
    -----
    Fails, in this order, when the plate barely moved or a channel did not (as
    :func:`poses_gate`, with each channel's range taken between its 0.5th and 99.5th
    percentiles, so that a few wild readings do not count as motion), and when the scans
    passed through fewer than :data:`MIN_POSES` (30) distinct positions. Whether the motion
    holds enough information is the ``min_singular``, ``condition`` and ``precision``
    gates' judgement, on the fit itself.
    """
    n = len(volts)
    k = distinct_positions(volts)
    move = ("move the plate by hand through its whole range for about two minutes, tilting "
            "it 25 deg or more toward each sensor")  # fmt: skip
    if n:
        lo, hi = np.percentile(volts, [0.5, 99.5], axis=0)
        failed = _motion_failure(hi - lo, k, f"{seconds:.0f} s of usable scans", move, "positions")
        if failed is not None:
            return failed
    if k < MIN_POSES:
        return Gate(
            "poses",
            False,
            k,
            f">= {MIN_POSES} positions",
            f"too little motion: the plate passed through only {k} distinct positions "
            f"({POSITION_CELL_V:g} V apart) in {seconds:.0f} s of usable scans",
            move,
        )
    return Gate("poses", True, k, f">= {MIN_POSES} positions")


def too_little_motion(positions: int, seconds: float, why: str, advice: Advice, *,
                      still: bool = False) -> str:  # fmt: skip
    """The advice of a gate whose failure follows from motion that did not tell the
    parameters apart: that cause first, and where to move the plate.

    Parameters
    ----------
    positions : int
        What the fit had: distinct positions of the usable scans
        (:func:`~loopcal.daemon.worker.coverage.distinct_positions`), or still poses.
    seconds : float
        The time they span, s.
    why : str
        What shows that the motion was too little, e.g. ``"condition, min_singular
        failed"`` or ``"A1x is known only to +-21.546 mm"``.
    advice : Advice
        Where to move the plate (:class:`~loopcal.daemon.worker.coverage.LazyAdvice`),
        made now.
    still : bool, default False
        The fit is on still poses (else on every scan).

    Returns
    -------
    str
        ``too little motion: 32 distinct positions over 5 s, the workspace is not covered
        (condition, min_singular failed): tilt the plate further toward sensor 2 (...), and
        record longer (about two minutes), then calibrate again``.
    """
    what = "still poses" if still else "distinct positions"
    return (f"too little motion: {positions} {what} over {seconds:.0f} s, the workspace is not "
            f"covered ({why}): {advice_text(advice)}, and record longer (about two minutes), "
            "then calibrate again")  # fmt: skip
