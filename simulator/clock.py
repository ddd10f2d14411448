"""Time bases for the emulated LDQ-412.

The device model never reads a clock itself: the emulator asks its clock for the current
time and hands it to the model, which then produces every scan due up to that instant.
Time is kept in integer nanoseconds so that scan schedules are exact and reproducible
(a float sum such as ``0.1 + 0.2`` must not move a scan across a boundary).

- :class:`RealClock`: wall time (monotonic), for running against real drivers.
- :class:`SimClock`: wall time sped up (or slowed down) by a constant factor.
- :class:`ManualClock`: time moves only when :meth:`ManualClock.advance` is called;
  the basis of every bit-exact test.
- :class:`HeldClock`: wall time that stands at 0 until :meth:`HeldClock.release` (a
  module switched on when its first client talks, whatever that client's start-up time).
- :class:`PlayClock`: wall time sped up, that runs only up to a limit its owner moves
  (a replay: it stops exactly at a scan, a power cycle, and waits there for a client).

All clocks start at 0 when created.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable

NS_PER_S = 1_000_000_000


@runtime_checkable
class Clock(Protocol):
    """A monotonic time base, in seconds since the clock was created.

    Anything with these two methods is a clock for the emulator
    (:class:`~loopcal.simulator.emulator.Emulator`); the device model only ever sees the
    integer nanoseconds of :meth:`now_ns`.
    """

    def now_ns(self) -> int:
        """Current time in integer nanoseconds (never decreases).

        Returns
        -------
        int
            Nanoseconds since the clock was created.
        """
        ...

    def now(self) -> float:
        """Current time in seconds (``now_ns() / 1e9``).

        Every clock here subclasses :class:`Clock` and so has this one.

        Returns
        -------
        float
            Seconds since the clock was created.
        """
        return self.now_ns() / NS_PER_S


class RealClock(Clock):
    """Wall time from :func:`time.monotonic_ns`, starting at 0 on creation."""

    def __init__(self) -> None:
        self._origin_ns = time.monotonic_ns()

    def now_ns(self) -> int:
        """Monotonic wall time since creation.

        Returns
        -------
        int
            Nanoseconds since the clock was created.
        """
        return time.monotonic_ns() - self._origin_ns


class SimClock(Clock):
    """Simulated time running ``speed`` times as fast as wall time.

    ``SimClock(10.0)`` makes one real second count as ten device seconds, so a 2 s power
    cycle takes 0.2 s of a test's wall time. The base of the clocks that run that fast
    only at times (:class:`HeldClock`, :class:`PlayClock`).

    Parameters
    ----------
    speed : float
        Simulated seconds per wall-clock second, > 0 (below 1 slows time down).

    Attributes
    ----------
    speed : float
        As given.

    Raises
    ------
    ValueError
        If ``speed`` is not > 0.
    """

    def __init__(self, speed: float) -> None:
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed!r}")
        self.speed = float(speed)
        self._origin_ns = time.monotonic_ns()  # the wall time it runs from

    def _run_since(self, origin_ns: int) -> int:
        """Wall nanoseconds since ``origin_ns`` (:func:`time.monotonic_ns`) times
        :attr:`speed`, truncated."""
        return int((time.monotonic_ns() - origin_ns) * self.speed)

    def now_ns(self) -> int:
        """Simulated time since creation.

        Returns
        -------
        int
            Wall nanoseconds since creation times :attr:`speed`, truncated.
        """
        return self._run_since(self._origin_ns)


def clock_for(speed: float) -> RealClock | SimClock:
    """Wall time running ``speed`` times as fast: a :class:`RealClock` at 1.

    Parameters
    ----------
    speed : float
        Simulated seconds per wall-clock second.

    Returns
    -------
    RealClock or SimClock
        A :class:`RealClock` when ``speed == 1.0``, else a :class:`SimClock`.

    Raises
    ------
    ValueError
        If ``speed`` is not > 0 (from :class:`SimClock`).
    """
    return RealClock() if speed == 1.0 else SimClock(speed)


class HeldClock(SimClock):
    """A :class:`SimClock` standing at 0 until :meth:`release`.

    An emulator on a HeldClock releases it at the first request it receives
    (:meth:`~loopcal.simulator.handle.DeviceHandle.note_request`): the module is switched
    on when its first client talks (``loopcal simulate --wait-for-client``).

    Parameters
    ----------
    speed : float, default 1.0
        Simulated seconds per wall-clock second once released (:class:`SimClock`'s).
    """

    def __init__(self, speed: float = 1.0) -> None:
        super().__init__(speed)
        self._released = False
        self._lock = threading.Lock()

    def release(self) -> None:
        """Start the clock (later calls do nothing); thread-safe."""
        with self._lock:
            if not self._released:
                self._origin_ns = time.monotonic_ns()
                self._released = True  # after the origin: a reader never sees an old one

    def now_ns(self) -> int:
        """Time since :meth:`release`.

        Returns
        -------
        int
            0 before :meth:`release`; after it, wall nanoseconds since the release times
            :attr:`speed`, truncated.
        """
        return self._run_since(self._origin_ns) if self._released else 0


class ManualClock(Clock):
    """A clock that only moves when told to; safe to advance from any thread.

    It starts at 0 and stands still between calls of :meth:`advance`: the basis of every
    bit-exact test (the same requests at the same clock readings give the same bytes).
    """

    def __init__(self) -> None:
        self._ns = 0
        self._lock = threading.Lock()

    def advance(self, seconds: float) -> None:
        """Move time forward by ``seconds``, rounded to the nearest nanosecond.

        Parameters
        ----------
        seconds : float
            How far to move, s, >= 0.

        Raises
        ------
        ValueError
            If ``seconds`` is negative.
        """
        if seconds < 0:
            raise ValueError(f"a clock cannot go backwards ({seconds!r} s)")
        with self._lock:
            self._ns += round(seconds * NS_PER_S)

    def now_ns(self) -> int:
        """The time the advances so far add up to.

        Returns
        -------
        int
            Nanoseconds since creation.
        """
        with self._lock:
            return self._ns


class PlayClock(SimClock):
    """A :class:`SimClock` that runs only up to a limit its owner moves.

    :meth:`run_until` lets it run from where it stands to ``limit_ns`` and stop there
    until the next call. Read at any instant it is exact (no steps), however late its
    owner's thread runs. It starts at 0, held there until the first :meth:`run_until`.
    A replay's :class:`~loopcal.simulator.replay.Player` drives one.

    Parameters
    ----------
    speed : float, default 1.0
        Simulated seconds per wall-clock second while it runs (:class:`SimClock`'s).
    """

    def __init__(self, speed: float = 1.0) -> None:
        super().__init__(speed)
        self._lock = threading.Lock()
        self._base_ns = 0  # where it stood when last told to run (at _origin_ns)
        self._limit_ns = 0

    def run_until(self, limit_ns: int) -> None:
        """Run on from now to ``limit_ns``, then stand still.

        Parameters
        ----------
        limit_ns : int
            Clock time to stop at, ns. Never back: a limit earlier than the time the clock
            shows holds it still where it is.
        """
        with self._lock:
            now = self._now_locked()
            self._base_ns, self._origin_ns = now, time.monotonic_ns()
            self._limit_ns = max(limit_ns, now)

    def _now_locked(self) -> int:
        return min(self._limit_ns, self._base_ns + self._run_since(self._origin_ns))

    def now_ns(self) -> int:
        """Where the clock stands.

        Returns
        -------
        int
            Nanoseconds: where it stood at the last :meth:`run_until`, plus the wall time
            since times :attr:`speed`, at most the limit.
        """
        with self._lock:
            return self._now_locked()
