"""An emulated LDQ-412 for other projects' integration tests: options, truth, fault injection.

What the pytest plugin (:mod:`loopcal.simulator.pytest_plugin`, fixtures ``ldq412`` and
``ldq412_factory``) hands a test, usable without pytest as well::

    from loopcal.simulator.testing import EmulatedLDQ412

    with EmulatedLDQ412(transport="ascii", seed=3) as module:
        daq = open_daq(module.url)        # any driver or Modbus client
        module.wait_scans(40)             # 2 s of scans at 20 Hz
        module.offset_step(3, +0.5)       # sensor 3's offset moves by 0.5 mm, now
        module.power_cycle()              # 2 s dark, then counter 0 and the restart bit
        module.truth.parameters           # the mechanism's true 20 parameters
        module.scans                      # every scan the module produced

The module is driven by a simulated shoulder joint (a technician's hand moving the plate,
the plate held still, a sweep, or the controller's task loop) with the true parameters of a
seeded mechanism, exactly as ``loopcal simulate`` serves it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import numbers
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from loopcal.calibration.parameters import to_dict
from loopcal.calibration.simulate import NOISE_VOLTS
from loopcal.drivers.ldq412 import POWER_CYCLE_S

from .choices import LINES, TRANSPORTS
from .clock import Clock, ManualClock, clock_for
from .device import TruthScan
from .drift import OffsetDrift, offset_shift
from .emulator import Emulator
from .faults import FaultInjector
from .mechanism import MechanismSource, true_parameters
from .open_points import OpenPoints
from .scenarios import SCENARIOS, scenario_named

CLOCKS = ("real", "manual")


@dataclass(frozen=True)
class LDQ412Options:
    """How the emulated module is built; every field has the default of ``loopcal simulate``.

    The options of the pytest plugin's fixtures and marker, and the keyword arguments of
    :class:`EmulatedLDQ412`.

    Attributes
    ----------
    transport : {"modbus-tcp", "modbus-rtu", "ascii"}, default "modbus-tcp"
        ``"modbus-tcp"`` (127.0.0.1, a free port), ``"modbus-rtu"`` or ``"ascii"`` (each
        on a pseudo-terminal whose path is in the URL, or as ``line`` says).
    line : {"pty", "tcp"}, default "pty"
        A serial transport's line: a pseudo-terminal, or raw TCP through a serial device
        server on 127.0.0.1 (:mod:`loopcal.simulator.device_server`).
    scan_rate_hz : int, default 20
        The module's scan rate at power-on, 1..200 Hz.
    speed : float, default 1.0
        Device seconds per real second, > 0 (a 10 makes a minute of scans in 6 s).
    clock : {"real", "manual"}, default "real"
        ``"real"`` (time passes by itself, ``speed`` times as fast) or ``"manual"`` (time
        moves only by :meth:`EmulatedLDQ412.advance`: the same requests give the same
        bytes; ``speed`` must stay 1).
    seed : int, default 0
        Seeds the mechanism's true parameters, the hand's moves and the noise.
    scenario : {"hand", "static", "sweep", "task"}, default "hand"
        ``"hand"`` (a technician's moves with still pauses), ``"static"`` (held at home),
        ``"sweep"`` (:mod:`loopcal.simulator.scenarios`) or ``"task"`` (the controller
        driving the plate round a fixed loop of waypoints for ever,
        :class:`~loopcal.simulator.task.TaskLoop`).
    pause_s : tuple of 2 float, default (1.0, 3.0)
        With ``"hand"``: (min, max) of each still pause, s, ``0 < min <= max``.
    task_waypoints : int, default 5
        With ``"task"``: the loop's waypoints (fixed orientations drawn from ``seed``),
        >= 2.
    task_move_s : float, default 2.0
        With ``"task"``: each move between two consecutive waypoints, s, > 0.
    task_dwell_s : float, default 0.5
        With ``"task"``: how long the plate stays at each waypoint, s, >= 0 (0: none).
    noise_volts : float, default NOISE_VOLTS
        Standard deviation of the noise per conversion, V, >= 0 (0.040 V).
    offset_error_mm : float, default 3.0
        The true offsets differ from the blueprint by up to this, mm.
    truth : mapping of str to float, default {}
        True parameters set exactly, ``{name: value}`` in the config's units (mm, mm/V),
        e.g. ``{"d03": 99.1}``.
    open_points : OpenPoints, default OpenPoints()
        The choices the datasheet leaves open (:mod:`loopcal.simulator.open_points`).
    unit : int, default 1
        The Modbus unit id, 1..247.
    ascii_addr : int, default 1
        The ASCII module address, 0..255.
    ascii_checksum : bool, default False
        The ASCII checksum mode at power-on.

    Raises
    ------
    ValueError
        If ``transport``, ``scenario`` or ``clock`` is not one of its choices, ``speed``
        is not a positive number (or not 1 with a manual clock), ``noise_volts`` is not a
        number >= 0, ``pause_s`` is not a range, a task loop setting is out of its
        range, or ``open_points`` is not an
        :class:`~loopcal.simulator.open_points.OpenPoints`; the message starts
        ``ldq412 option`` and names it.

    Notes
    -----
    ``scan_rate_hz``, ``offset_error_mm``, ``truth``, ``unit`` and ``ascii_addr`` are
    checked when the module is built (:class:`EmulatedLDQ412` raises ValueError naming
    them).
    """

    transport: str = "modbus-tcp"
    line: str = LINES[0]
    scan_rate_hz: int = 20
    speed: float = 1.0
    clock: str = "real"
    seed: int = 0
    scenario: str = "hand"
    pause_s: tuple[float, float] = (1.0, 3.0)
    task_waypoints: int = 5
    task_move_s: float = 2.0
    task_dwell_s: float = 0.5
    noise_volts: float = NOISE_VOLTS
    offset_error_mm: float = 3.0
    truth: Mapping[str, float] = field(default_factory=dict)
    open_points: OpenPoints = field(default_factory=OpenPoints)
    unit: int = 1
    ascii_addr: int = 1
    ascii_checksum: bool = False

    def __post_init__(self) -> None:
        def bad(what: str) -> ValueError:
            return ValueError(f"ldq412 option {what}")

        if self.transport not in TRANSPORTS:
            raise bad(f"transport={self.transport!r}: one of {', '.join(TRANSPORTS)}")
        if self.line not in LINES:
            raise bad(f"line={self.line!r}: one of {', '.join(LINES)}")
        if self.scenario not in SCENARIOS:
            raise bad(f"scenario={self.scenario!r}: one of {', '.join(SCENARIOS)}")
        if self.clock not in CLOCKS:
            raise bad(f"clock={self.clock!r}: one of {', '.join(CLOCKS)}")
        if not isinstance(self.speed, int | float) or not self.speed > 0:
            raise bad(f"speed={self.speed!r}: a positive number of device seconds per second")
        if self.clock == "manual" and self.speed != 1.0:
            raise bad("speed: a manual clock moves only when advanced (leave speed at 1)")
        if not isinstance(self.noise_volts, int | float) or not self.noise_volts >= 0:
            raise bad(f"noise_volts={self.noise_volts!r}: volts, >= 0")
        lo, hi = self.pause_s
        if not 0 < lo <= hi:
            raise bad(f"pause_s={self.pause_s!r}: (min, max) seconds with 0 < min <= max")
        n = self.task_waypoints
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 2:
            raise bad(f"task_waypoints={n!r}: an integer, 2 or more")
        for what, value, least in (("task_move_s", self.task_move_s, None),
                                   ("task_dwell_s", self.task_dwell_s, 0.0)):  # fmt: skip
            ok = isinstance(value, numbers.Real) and np.isfinite(value)
            if not (ok and (value > 0 if least is None else value >= least)):
                need = "> 0" if least is None else ">= 0"
                raise bad(f"{what}={value!r}: seconds, {need}")
        if not isinstance(self.open_points, OpenPoints):
            raise bad("open_points: a loopcal.simulator.open_points.OpenPoints")

    @classmethod
    def from_mapping(cls, options: Mapping[str, Any]) -> LDQ412Options:
        """Options from keyword arguments, an unknown name a clear error.

        Parameters
        ----------
        options : mapping of str to object
            Field names and values; fields not given keep their defaults.

        Returns
        -------
        LDQ412Options

        Raises
        ------
        TypeError
            If a name is not a field (``unknown ldq412 option(s) ...; the options are
            ...``).
        ValueError
            If a value is refused (see the class).
        """
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise TypeError(
                f"unknown ldq412 option(s) {', '.join(map(repr, unknown))}; "
                f"the options are {', '.join(sorted(known))}"
            )
        return cls(**options)


@dataclass
class Truth:
    """What the emulated mechanism really is, for a test to compare against.

    Attributes
    ----------
    parameters : ndarray of float, shape (20,)
        The 20 true parameters in the order of
        :data:`loopcal.calibration.parameters.NAMES`, in the config's units (mm; mm/V for
        the gains ``S1``..``S4``).
    scenario : dict
        The plate's motion, as ``loopcal simulate --truth-out`` describes it
        (:meth:`Scenario.describe <loopcal.simulator.motion.Scenario.describe>`).
    noise_volts : float
        Standard deviation of the noise per conversion, V, as built.
    seed : int
        As built.
    drifts : list of OffsetDrift
        The offset drifts injected so far (:class:`~loopcal.simulator.drift.OffsetDrift`,
        times in seconds since the module was first switched on); the very list the
        simulated mechanism reads.
    """

    parameters: np.ndarray
    scenario: dict
    noise_volts: float
    seed: int
    drifts: list[OffsetDrift] = field(default_factory=list)

    def as_dict(self) -> dict[str, float]:
        """The true parameters by name.

        Returns
        -------
        dict of str to float
            ``{name: value}`` for the 20 parameters, e.g. ``{"d01": 101.3, ...}`` (mm,
            mm/V).
        """
        return to_dict(self.parameters)

    def offset_shift_mm(self, t_s: float) -> np.ndarray:
        """Each sensor's offset change at a time, from the drifts injected so far.

        Parameters
        ----------
        t_s : float
            Source time, s since the module was first switched on (a scan's ``t_s``, or
            :attr:`EmulatedLDQ412.time_s` for now).

        Returns
        -------
        ndarray of float, shape (4,)
            Sensor 1..4's offset change, mm: a length ``d`` reads as ``d - shift``.
        """
        return offset_shift(self.drifts, np.full(4, float(t_s)))


class EmulatedLDQ412(contextlib.AbstractContextManager):
    """An emulated LDQ-412 on a real transport, started on construction; a context manager.

    Close it (or leave the ``with``) to stop its servers and free its port or
    pseudo-terminal. The module is driven by a simulated shoulder joint
    (:class:`~loopcal.simulator.mechanism.MechanismSource`) with the true parameters of a
    seeded mechanism, exactly as ``loopcal simulate`` serves it.

    Parameters
    ----------
    options : LDQ412Options or None, default None
        How to build it.
    **kwargs
        :class:`LDQ412Options` fields instead of ``options``.

    Attributes
    ----------
    options : LDQ412Options
        As built.
    truth : Truth
        The mechanism's true parameters, scenario, noise, seed and drifts.
    emulator : Emulator
        The :class:`~loopcal.simulator.emulator.Emulator` underneath.

    Raises
    ------
    TypeError
        If both ``options`` and keyword options are given, or a keyword is not an option.
    ValueError
        If an option's value is refused (the message names it).
    RuntimeError
        If the servers could not start
        (:meth:`~loopcal.simulator.emulator.Emulator.start`).
    TimeoutError
        If they were not up within 5 s.
    """

    def __init__(self, options: LDQ412Options | None = None, **kwargs: Any) -> None:
        if options is not None and kwargs:
            raise TypeError("give options= or keyword options, not both")
        self.options = options or LDQ412Options.from_mapping(kwargs)
        o = self.options
        params = true_parameters(o.seed, o.offset_error_mm, o.truth)
        scenario = scenario_named(o.scenario, seed=o.seed, params=params, pause_s=o.pause_s,
                                  waypoints=o.task_waypoints, move_s=o.task_move_s,
                                  dwell_s=o.task_dwell_s)  # fmt: skip
        self._source = MechanismSource(scenario, params, noise_volts=o.noise_volts, seed=o.seed)
        # the mechanism's own list: what the module scans with is what a test is told
        self.truth = Truth(params.copy(), scenario.describe(), float(o.noise_volts), o.seed,
                           self._source.drifts)  # fmt: skip
        clock: Clock = ManualClock() if o.clock == "manual" else clock_for(o.speed)
        self.emulator = Emulator(
            o.transport,
            self._source,
            scan_rate_hz=o.scan_rate_hz,
            clock=clock,
            seed=o.seed,
            unit=o.unit,
            ascii_addr=o.ascii_addr,
            ascii_checksum=o.ascii_checksum,
            open_points=o.open_points,
            line=o.line,
        )
        self.emulator.start()

    # ------------------------------------------------------------------ what it is

    @property
    def url(self) -> str:
        """The URL a driver opens (:func:`loopcal.drivers.open_daq`).

        ``modbus-tcp://127.0.0.1:PORT?unit=1``,
        ``modbus-rtu:///dev/pts/N?baud=115200&unit=1`` or ``ascii:///dev/pts/N?...``.
        """
        return self.emulator.url

    @property
    def transport(self) -> str:
        """``"modbus-tcp"``, ``"modbus-rtu"`` or ``"ascii"``, as built."""
        return self.options.transport

    @property
    def port(self) -> str | int:
        """The TCP port (modbus-tcp, or a serial device server's), else the pseudo-terminal
        a serial client opens.

        An int on TCP; a path such as ``/dev/pts/7`` for a serial transport on a pty.
        """
        if self.emulator.link is None:
            return self.emulator.port
        return self.url.split("://", 1)[1].split("?", 1)[0]

    @property
    def clock(self) -> Clock:
        """The module's clock (:class:`~loopcal.simulator.clock.Clock`).

        A :class:`~loopcal.simulator.clock.ManualClock` with ``clock="manual"``, else a
        :class:`~loopcal.simulator.clock.RealClock` (or a
        :class:`~loopcal.simulator.clock.SimClock` at another ``speed``).
        """
        return self.emulator.clock

    @property
    def faults(self) -> FaultInjector:
        """Every fault the emulator knows (garbage bytes, corrupt answers, stuck channels,
        sensor faults, saturation, latency): :class:`~loopcal.simulator.faults.FaultInjector`."""
        return self.emulator.faults

    @property
    def scans(self) -> list[TruthScan]:
        """Every scan the module produced so far, in order (ground truth, a copy).

        A list of :class:`~loopcal.simulator.device.TruthScan`: counter, device time,
        codes, status, source time and power-on index of each.
        """
        return self.emulator.truth

    @property
    def time_s(self) -> float:
        """Seconds since the module was first switched on (the drifts' time axis)."""
        with self.emulator.handle.synced() as device:
            return device.source_time_s

    # ------------------------------------------------------------------ time

    def advance(self, seconds: float) -> None:
        """Move a manual clock forward (``clock="manual"`` only).

        The module takes every scan due meanwhile when it is next looked at.

        Parameters
        ----------
        seconds : float
            Device seconds, >= 0.

        Raises
        ------
        RuntimeError
            If the clock is not manual.
        ValueError
            If ``seconds`` is negative.
        """
        if not isinstance(self.clock, ManualClock):
            raise RuntimeError("advance() needs clock='manual'; a real clock moves by itself")
        self.clock.advance(seconds)

    def wait_scans(self, n: int, timeout: float = 10.0) -> list[TruthScan]:
        """Wait until the module has produced ``n`` more scans, and return them.

        A manual clock is advanced scan by scan (one period at a time); a real one is
        waited for.

        Parameters
        ----------
        n : int
            How many scans, >= 0, counted from the call.
        timeout : float, default 10.0
            Longest wait, real seconds.

        Returns
        -------
        list of TruthScan
            The ``n`` scans produced after the call, in order.

        Raises
        ------
        ValueError
            If ``n`` is negative.
        TimeoutError
            If they did not come within ``timeout`` (a module powered off, say).
        """
        if n < 0:
            raise ValueError("n must be >= 0")
        before = len(self.scans)
        deadline = time.monotonic() + timeout
        manual = isinstance(self.clock, ManualClock)
        step = 1.0 / self.options.scan_rate_hz
        while True:
            scans = self.scans
            if len(scans) - before >= n:
                return scans[before : before + n]
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"the module produced {len(scans) - before} of {n} scans in {timeout} s"
                )
            if manual:
                self.clock.advance(step)
            else:
                time.sleep(min(step / self.options.speed, 0.02))

    # ------------------------------------------------------------------ faults

    def power_cycle(self, off_s: float = POWER_CYCLE_S) -> None:
        """Switch the module off now and on ``off_s`` device seconds later.

        Then the datasheet's power-on: counter 0, device time 0, the restart flag set, the
        FIFO empty (:meth:`~loopcal.simulator.faults.FaultInjector.restart`).

        Parameters
        ----------
        off_s : float, default POWER_CYCLE_S
            How long it is dark, device seconds (2 s).
        """
        self.faults.restart(off_s)

    def disconnect(self) -> None:
        """Cut the link (TCP: connections reset and the port closed; serial: silence)."""
        self.faults.disconnect()

    def reconnect(self) -> None:
        """Restore the link after :meth:`disconnect`."""
        self.faults.reconnect()

    def stall(self, seconds: float) -> None:
        """No answers for ``seconds`` (>= 0) of device time; the module keeps scanning
        (:meth:`~loopcal.simulator.faults.FaultInjector.stall`: what ends it, its errors)."""
        self.faults.stall(seconds)

    def offset_step(self, sensor: int, mm: float, duration: float | None = None) -> OffsetDrift:
        """Sensor ``sensor`` reads as if its offset moved by ``mm`` from now on.

        A loose core or a refitted LVDT: a length ``d`` reads as ``d - mm``. Scans already
        due are not affected.

        Parameters
        ----------
        sensor : int
            1..4.
        mm : float
            The step, mm, either sign.
        duration : float or None, default None
            How long, s (then the offset goes back); None: for good.

        Returns
        -------
        OffsetDrift
            The drift, also in :attr:`Truth.drifts`.

        Raises
        ------
        ValueError
            If ``sensor`` is not 1..4, ``mm`` not finite or ``duration`` not positive.
        """
        return self._drift("step", sensor, mm, duration)

    def offset_creep(
        self, sensor: int, mm_per_min: float, duration: float | None = None
    ) -> OffsetDrift:
        """Sensor ``sensor``'s offset creeps by ``mm_per_min`` (mm per minute, either sign)
        from now on, for ``duration`` s (then the offset is held; None: for ever).

        The sensor, the duration, what it returns and when it raises ValueError (for
        ``mm_per_min`` as for ``mm``): as :meth:`offset_step`.
        """
        return self._drift("creep", sensor, mm_per_min, duration)

    def _drift(self, kind: str, sensor: int, amount: float, duration: float | None) -> OffsetDrift:
        # taken under the device's lock, synced to now: scans already due are not affected
        with self.emulator.handle.synced() as device:
            drift = OffsetDrift(kind, sensor, device.source_time_s, float(amount), duration)
            self._source.drifts.append(drift)
        return drift

    # ------------------------------------------------------------------ lifetime

    def close(self) -> None:
        """Stop the servers and free the port or pseudo-terminal. Idempotent."""
        self.emulator.close()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"EmulatedLDQ412({self.url!r}, seed={self.options.seed})"
