"""The serving of ``loopcal simulate``: an emulated LDQ-412 driven by a simulated shoulder
joint (:func:`run`), its scheduled faults (:class:`FaultEvent`) and its ground truth streamed
to a JSON Lines file (:class:`TruthWriter`). The command's options and its description are
:mod:`loopcal.simulator.arguments`' (which a ``--help`` reads without numpy).
"""

from __future__ import annotations

import argparse
import json
import re
import signal
import threading
from dataclasses import dataclass
from typing import TextIO

import numpy as np

from loopcal.calibration.kinematics import euler_zyz
from loopcal.calibration.parameters import NAMES, to_dict

from .arguments import DESCRIPTION
from .clock import Clock, HeldClock, clock_for
from .drift import OffsetDrift
from .emulator import Emulator
from .faults import FaultInjector
from .mechanism import MechanismSource, ReplaySource, true_parameters
from .open_points import from_arguments as open_points_from_arguments
from .options import SimulationError, check_simulation_options
from .scenarios import scenario_named

_FAULT = re.compile(
    r"^(?P<kind>[a-z]+)@(?P<at>\d+(?:\.\d*)?)(?:\+(?P<dur>\d+(?:\.\d*)?))?(?::(?P<arg>.+))?$"
)
_KINDS = (
    "restart", "stall", "disconnect", "garbage", "corrupt", "stuck", "sensor", "saturate",
    "offset", "creep",
)  # fmt: skip
DRIFT_KINDS = {"offset": "step", "creep": "creep"}


@dataclass(frozen=True)
class FaultEvent:
    """A scheduled fault of ``loopcal simulate --fault``: on at ``at``, off at ``at + duration``.

    The syntax is ``KIND@SECONDS[+DURATION][:ARG]`` (``loopcal simulate --help-faults``:
    :data:`~loopcal.simulator.arguments.DESCRIPTION`).

    Attributes
    ----------
    kind : str
        One of restart, stall, disconnect, garbage, corrupt, stuck, sensor, saturate,
        offset, creep.
    at : float
        When it is switched on, device seconds since the start.
    duration : float or None
        How long it lasts, s: the time off for a restart, the length of a stall, and when
        the lasting ones (disconnect, stuck, sensor, saturate) are switched off; None where
        not given.
    channel : int or None
        The channel (sensor) 1..4 of stuck, sensor, saturate, offset and creep.
    value : str or None
        The argument as given: a code (stuck), ``high``/``low`` (saturate), mm (offset),
        mm per minute (creep), a count (garbage, default 16; corrupt, default 1).
    """

    kind: str
    at: float
    duration: float | None
    channel: int | None
    value: str | None

    @classmethod
    def parse(cls, text: str) -> FaultEvent:
        """One ``--fault`` specification.

        Parameters
        ----------
        text : str
            ``KIND@SECONDS[+DURATION][:ARG]``, e.g. ``restart@30``, ``stall@12+2``,
            ``stuck@15+5:2=1000``, ``offset@30:3=+0.5``.

        Returns
        -------
        FaultEvent

        Raises
        ------
        ValueError
            If the text does not match the syntax, names an unknown kind, lacks a duration
            a lasting fault needs, or has a channel or argument out of range; the message
            quotes the text.
        """
        m = _FAULT.match(text.strip())
        if not m or m["kind"] not in _KINDS:
            raise ValueError(
                f"bad fault {text!r}: expected KIND@SECONDS[+DURATION][:ARG] with KIND one of "
                f"{', '.join(_KINDS)} (e.g. restart@30, stall@12+2, stuck@15+5:2=1000)"
            )
        kind, arg = m["kind"], m["arg"]
        dur = float(m["dur"]) if m["dur"] else None
        channel = value = None
        if kind in ("stall", "disconnect", "stuck", "sensor", "saturate") and dur is None:
            raise ValueError(f"fault {text!r} needs a duration: {kind}@SECONDS+DURATION")
        if kind in ("stuck", "sensor", "saturate", "offset", "creep"):
            ch, _, value = (arg or "").partition("=")
            if ch not in ("1", "2", "3", "4"):
                raise ValueError(f"fault {text!r} needs a channel 1..4 after ':'")
            channel = int(ch)
            if kind == "stuck" and not (value.isdigit() and 0 <= int(value) <= 4095):
                raise ValueError(f"fault {text!r}: stuck needs a code 0..4095 (:CH=CODE)")
            if kind == "saturate" and value not in ("high", "low"):
                raise ValueError(f"fault {text!r}: saturate needs :CH=high or :CH=low")
            if kind in DRIFT_KINDS:
                try:
                    ok = np.isfinite(float(value))
                except ValueError:
                    ok = False
                if not ok:
                    unit = "mm" if kind == "offset" else "mm per minute"
                    raise ValueError(f"fault {text!r}: {kind} needs :CH=AMOUNT in {unit}")
        elif kind in ("garbage", "corrupt"):
            value = arg or ("16" if kind == "garbage" else "1")
            if not value.isdigit() or int(value) < 1:
                raise ValueError(f"fault {text!r}: {kind} takes a positive count")
        return cls(kind, float(m["at"]), dur, channel, value)

    def drift(self) -> OffsetDrift | None:
        """The offset drift this fault is (offset, creep), else None.

        Drifts are functions of device time inside the simulated mechanism, not switched
        by the fault loop.

        Returns
        -------
        OffsetDrift or None
            A step of ``value`` mm, or a creep of ``value`` mm per minute, on ``channel``
            from ``at`` for ``duration``.
        """
        if self.kind not in DRIFT_KINDS:
            return None
        return OffsetDrift(
            DRIFT_KINDS[self.kind], self.channel, self.at, float(self.value), self.duration
        )

    def switch_on(self, f: FaultInjector) -> None:
        """Start the fault on a running emulator (drifts do nothing here).

        Parameters
        ----------
        f : FaultInjector
            The emulator's fault injection (``Emulator.faults``).
        """
        k = self.kind
        if k == "restart":
            f.restart(self.duration if self.duration is not None else 2.0)
        elif k == "stall":
            f.stall(self.duration)
        elif k == "disconnect":
            f.disconnect()
        elif k == "garbage":
            f.garbage(int(self.value))
        elif k == "corrupt":
            f.corrupt_next(int(self.value))
        elif k == "stuck":
            f.stuck_channel(self.channel, int(self.value))
        elif k == "sensor":
            f.sensor_fault(self.channel, True)
        elif k == "saturate":
            f.saturate(self.channel, self.value)

    def switch_off(self, f: FaultInjector) -> None:
        """End a lasting fault (disconnect, stuck, sensor, saturate); nothing for the others.

        The others end by themselves (a stall, a power cycle) or act once.

        Parameters
        ----------
        f : FaultInjector
            The emulator's fault injection.
        """
        k = self.kind
        if k == "disconnect":
            f.reconnect()
        elif k == "stuck":
            f.stuck_channel(self.channel, None)
        elif k == "sensor":
            f.sensor_fault(self.channel, False)
        elif k == "saturate":
            f.saturate(self.channel, None)


class TruthWriter:
    """Streams ground truth as JSON Lines: a header, then one object per scan.

    The header line is written at construction: ``{"type": "header", **header}``.

    Parameters
    ----------
    out : text file
        Where to write (flushed after each batch).
    header : dict
        The header's fields (parameters, scenario, noise, seed, transport, ...).
    source : MechanismSource or ReplaySource
        The module's source: a mechanism's scenario gives each scan's true plate
        orientation.

    Attributes
    ----------
    out : text file
        As given.
    source : MechanismSource or ReplaySource
        As given.
    last : tuple of 2 int, or None
        ``(boot, counter)`` of the last scan written (None: none yet).
    """

    def __init__(self, out: TextIO, header: dict, source: MechanismSource | ReplaySource) -> None:
        self.out = out
        self.source = source
        self.last: tuple[int, int] | None = None  # (boot, counter) last written
        out.write(json.dumps({"type": "header", **header}) + "\n")

    def write_new(self, truth: list) -> int:
        """Write the scans of ``truth`` after the last one written.

        Each is ``{"type": "scan", "boot", "counter", "time_us", "codes", "status",
        "t_s", "euler_deg"}``: ``t_s`` in s, ``euler_deg`` the plate's true Z-Y-Z Euler
        angles in degrees (None for a replay).

        Parameters
        ----------
        truth : list of TruthScan
            The emulator's scans, in order (:attr:`Emulator.truth
            <loopcal.simulator.emulator.Emulator.truth>`); those up to the last written
            one are skipped (all are written if it is not among them).

        Returns
        -------
        int
            How many scans were written.
        """
        start = 0
        if self.last is not None:
            for i in range(len(truth) - 1, -1, -1):
                if (truth[i].boot, truth[i].counter) == self.last:
                    start = i + 1
                    break
        new = truth[start:]
        if not new:
            return 0
        scenario = getattr(self.source, "scenario", None)
        euler = (
            np.degrees(euler_zyz(scenario.rotation([s.t_s for s in new])))
            if scenario is not None
            else [None] * len(new)
        )
        for s, e in zip(new, euler, strict=True):
            rec = {
                "type": "scan",
                "boot": s.boot,
                "counter": s.counter,
                "time_us": s.time_us,
                "codes": list(s.codes),
                "status": s.status,
                "t_s": round(s.t_s, 6),
                "euler_deg": None if e is None else [round(float(a), 6) for a in e],
            }
            self.out.write(json.dumps(rec) + "\n")
        self.last = (new[-1].boot, new[-1].counter)
        self.out.flush()
        return len(new)


def truth_parameters(args: argparse.Namespace) -> np.ndarray:
    """The true parameters ``loopcal simulate`` asks for: seeded, then ``--truth`` overrides.

    Offsets (and the paper's geometry) moved at random by the seed, then explicit
    ``NAME=VALUE`` overrides (``--truth``).

    Parameters
    ----------
    args : argparse.Namespace
        ``loopcal simulate``'s arguments: ``truth`` (``"NAME=VALUE,..."`` or None),
        ``seed``, ``offset_error`` (mm).

    Returns
    -------
    ndarray of float, shape (20,)
        As :func:`~loopcal.simulator.mechanism.true_parameters` makes them.

    Raises
    ------
    ValueError
        If an entry is not ``NAME=VALUE`` with one of the 20 names and a number, or
        :func:`~loopcal.simulator.mechanism.true_parameters` refuses the values.
    """
    overrides = {}
    for item in filter(None, (s.strip() for s in (args.truth or "").split(","))):
        name, eq, value = item.partition("=")
        if not eq or name.strip() not in NAMES:
            raise ValueError(
                f"bad --truth entry {item!r}: expected NAME=VALUE, NAME one of the 20 parameters"
            )
        try:
            overrides[name.strip()] = float(value)
        except ValueError:
            raise ValueError(f"bad --truth entry {item!r}: {value!r} is not a number") from None
    return true_parameters(args.seed, args.offset_error, overrides)


#: ``loopcal simulate``'s task loop options: (option, argument name, TaskLoop's keyword)
TASK_OPTIONS = (
    ("--task-waypoints", "task_waypoints", "waypoints"),
    ("--task-move", "task_move", "move_s"),
    ("--task-dwell", "task_dwell", "dwell_s"),
)


def task_settings(args: argparse.Namespace) -> dict[str, float]:
    """The task loop's settings ``loopcal simulate`` was given, checked.

    Parameters
    ----------
    args : argparse.Namespace
        ``loopcal simulate``'s arguments: ``scenario``, and ``task_waypoints``,
        ``task_move``, ``task_dwell`` (each None where not given).

    Returns
    -------
    dict of str to float
        The given ones as :class:`~loopcal.simulator.task.TaskLoop`'s keywords
        (``waypoints``, ``move_s`` in s, ``dwell_s`` in s); those not given are left to
        its defaults.

    Raises
    ------
    ValueError
        If one is given with another scenario than ``task`` (naming the options given
        and the scenario), ``--task-waypoints`` is under 2, ``--task-move`` is not a
        finite number of seconds above 0, or ``--task-dwell`` not one of 0 or more.
    """
    given = {opt: getattr(args, dest) for opt, dest, _ in TASK_OPTIONS
             if getattr(args, dest, None) is not None}  # fmt: skip
    if given and args.scenario != "task":
        raise ValueError(f"{', '.join(given)} only with --scenario task, not --scenario "
                         f"{args.scenario}")  # fmt: skip
    waypoints, move, dwell = (given.get(opt) for opt, _, _ in TASK_OPTIONS)
    if waypoints is not None and waypoints < 2:
        raise ValueError(f"--task-waypoints must be 2 or more, got {waypoints}")
    if move is not None and not (np.isfinite(move) and move > 0):
        raise ValueError(f"--task-move must be a number of seconds above 0, got {move:g}")
    if dwell is not None and not (np.isfinite(dwell) and dwell >= 0):
        raise ValueError(f"--task-dwell must be 0 or more seconds, got {dwell:g}")
    return {key: given[opt] for opt, _, key in TASK_OPTIONS if opt in given}


def run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """Serve until ``--duration`` of device time has passed or SIGINT/SIGTERM.

    ``loopcal simulate``: prints the URL (and a serial transport's device), applies the
    scheduled faults and streams the truth file.

    Parameters
    ----------
    args : argparse.Namespace
        The options :func:`add_arguments` added.
    stop : threading.Event or None, default None
        Set it to stop early (SIGINT and SIGTERM set it when run in the main thread).

    Returns
    -------
    int
        The exit status: 0 after serving (or ``--help-faults``).

    Raises
    ------
    SimulationError
        For bad options, a truth file that cannot be written or servers that cannot start
        (:class:`~loopcal.simulator.options.SimulationError`; the command line prints it).
    TimeoutError
        If the servers were not up within 5 s (not turned into an exit status).
    """
    if args.help_faults:
        print(DESCRIPTION)
        return 0
    try:
        faults = sorted((FaultEvent.parse(s) for s in args.fault), key=lambda e: e.at)
        truth = truth_parameters(args)
        check_simulation_options(args)
        task = task_settings(args)
        drifts = tuple(d for d in (e.drift() for e in faults) if d is not None)
        open_points = open_points_from_arguments(args)
        if args.replay is not None and args.scenario != "replay":
            raise ValueError(f"--replay only with --scenario replay, not --scenario "
                             f"{args.scenario}")  # fmt: skip
        if args.scenario == "replay":
            if args.replay is None:
                raise ValueError("--scenario replay needs --replay FILE")
            if drifts:
                raise ValueError("offset and creep faults need a simulated mechanism, not a replay")
            source = ReplaySource.from_truth_file(args.replay, loop=True)
            scenario = None
        else:
            scenario = scenario_named(
                args.scenario, seed=args.seed, params=truth, pause_s=args.pause,
                twist_every=args.twist_every, **task,
            )  # fmt: skip
            source = MechanismSource(
                scenario, truth, noise_volts=args.noise_mv / 1000, seed=args.seed, drifts=drifts
            )
        if args.duration is not None and not args.duration > 0:
            raise ValueError("--duration must be positive")
        # opened now: a truth file that cannot be written is an error before anything runs
        out = open(args.truth_out, "w", encoding="utf-8") if args.truth_out else None  # noqa: SIM115
    except (ValueError, OSError) as exc:
        what = f"--truth-out {args.truth_out}: " if isinstance(exc, OSError) else ""
        raise SimulationError(f"{what}{exc}") from None
    # a held clock is released by the emulator's first request
    clock: Clock = HeldClock(args.speed) if args.wait_for_client else clock_for(args.speed)
    stop = stop or threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        if threading.current_thread() is threading.main_thread():
            signal.signal(sig, lambda *_: stop.set())
    emu = Emulator(
        args.transport,
        source,
        scan_rate_hz=args.scan_rate,
        clock=clock,
        seed=args.seed,
        unit=args.unit,
        ascii_addr=args.addr,
        ascii_checksum=args.checksum,
        host=args.host,
        port=args.port,
        truth_limit=max(20_000, int(60 * args.scan_rate * args.speed)),
        open_points=open_points,
        line=args.line,
    )
    try:
        try:
            emu.start()
        except RuntimeError as exc:
            raise SimulationError(str(exc)) from None
        with emu:
            print(f"listening: {emu.url}", flush=True)
            if emu.link is not None:
                print(f"serial device: {emu.url.split('://', 1)[1].split('?')[0]}", flush=True)
            writer = None
            if out is not None:
                header = {
                    "parameters": to_dict(truth) if scenario else None,
                    "scenario": scenario.describe()
                    if scenario
                    else {"name": "replay", "file": str(args.replay)},
                    "noise_volts": args.noise_mv / 1000,
                    "seed": args.seed,
                    "transport": args.transport,
                    "scan_rate_hz": args.scan_rate,
                    "url": emu.url,
                    "faults": args.fault,
                    "open_points": {k: str(v) for k, v in open_points.changed().items()},
                }
                writer = TruthWriter(out, header, source)
            t0 = clock.now()
            pending = [(e.at, 0, e) for e in faults]
            pending += [
                (e.at + e.duration, 1, e)
                for e in faults
                if e.duration is not None
                and e.kind in ("disconnect", "stuck", "sensor", "saturate")
            ]
            pending.sort(key=lambda x: (x[0], x[1]))
            last_flush = 0.0
            while not stop.is_set():
                now = clock.now() - t0
                while pending and pending[0][0] <= now:
                    _, off, event = pending.pop(0)
                    (event.switch_off if off else event.switch_on)(emu.faults)
                    print(f"{now:9.3f} s  fault {'off' if off else 'on'}: {event.kind}", flush=True)
                if writer is not None and clock.now() - t0 - last_flush >= 0.5 * args.speed:
                    writer.write_new(emu.truth)
                    last_flush = clock.now() - t0
                if args.duration is not None and now >= args.duration:
                    break
                stop.wait(0.05)
            if writer is not None:
                writer.write_new(emu.truth)
    finally:
        if out is not None:
            out.close()
    return 0
