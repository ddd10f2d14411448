"""What the datasheet leaves open, as settings of the emulated module.

A module built by someone else makes other choices than ours wherever the datasheet is
silent or loose, and the drivers must survive all of them. Each setting below names the
datasheet line it varies; every default is what the emulator did before it had the
setting, so an :class:`OpenPoints` () module is the emulator as it always was.

- ``scan_phase_us``: "Every scan gets a 32-bit scan counter (starts at 0 at power-on ...)"
  does not say when scan 0 is taken. Default 0 (at power-on); a module may take it later,
  e.g. 1809 µs after power-on. The module answers nothing before its first scan.
- ``clock_ppm``: "The module scans on its own clock" does not say how good that clock is.
  Its rate error against the host's, parts per million: +200 makes a 20 Hz module scan at
  20.004 Hz by the host's clock (device time counts the module's own µs, so it runs 200
  ppm fast as well).
- ``latency``: "Modbus RTU answers within 5 ms, TCP within 10 ms on a quiet network, ASCII
  within 10 ms. A host should treat 100 ms without an answer as a timeout." Default: at
  once. :class:`Latency` draws each answer's delay, with occasional slow answers (50-90
  ms) that are still not timeouts.
- ``fifo_underrun``: "asking for more scans than are waiting returns the waiting ones
  followed by all-0xFFFF filler scans". ``"filler"`` (default) does that; ``"short"``
  answers only the waiting scans (a partial read: fewer registers than asked).
- ``max_read_registers`` and ``over_limit``: "N is at most 20 per request" (120
  registers; Modbus allows 125). A module may take fewer registers per request:
  ``"refuse"`` answers a longer read with exception 03, ``"truncate"`` answers only the
  first ``max_read_registers`` (whole scans in the FIFO window, the rest left waiting).
- ``holes``: the input register table lists 0-9, 256.. and 512-515 only. ``"refuse"``
  (default) answers exception 02 to a read that leaves them (one spanning the snapshot
  and the FIFO window, say); ``"zero"`` reads 0 there.
- ``snapshot_reads``: "A single read of registers 0..9 is one consistent snapshot".
  ``"any"`` (default) also answers reads of part of it; ``"whole"`` refuses them (02).
"""

from __future__ import annotations

import argparse
import re
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:  # for a type only: the options are added by a --help, without numpy
    import numpy as np

#: The datasheet's answer-time bound per transport, ms ("Timing").
DATASHEET_LATENCY_MS = {"modbus-tcp": 10.0, "modbus-rtu": 5.0, "ascii": 10.0}
#: Modbus' own limit on the registers of one read (application protocol spec).
MODBUS_MAX_READ = 125

_LATENCY = re.compile(r"^(?:(?P<ds>datasheet)|(?P<lo>\d+(?:\.\d*)?)(?:-(?P<hi>\d+(?:\.\d*)?))?)$")


@dataclass(frozen=True)
class Latency:
    """How long the module takes to answer a request, wall-clock ms.

    Each answer waits ``uniform(min_ms, max_ms)`` (``max_ms`` None: the datasheet's bound
    for the transport, 10 ms TCP and ASCII, 5 ms RTU); with probability ``slow_fraction``
    it waits ``uniform(*slow_ms)`` instead. What the answer says is decided when the
    request arrives (a FIFO read pops its scans then); only sending it is delayed, and
    answers leave in the order their requests came.

    Attributes
    ----------
    min_ms : float, default 0.5
        Shortest ordinary answer time, ms, >= 0.
    max_ms : float or None, default None
        Longest ordinary answer time, ms, >= ``min_ms``; None: the datasheet's bound for
        the transport (:data:`DATASHEET_LATENCY_MS`).
    slow_fraction : float, default 0.0
        Probability of a slow answer, 0..1.
    slow_ms : tuple of 2 float, default (50.0, 90.0)
        (min, max) of a slow answer's time, ms: slower than the datasheet allows, still
        faster than a host's 100 ms timeout.

    Raises
    ------
    ValueError
        If ``min_ms`` is negative or above ``max_ms``, ``slow_fraction`` is outside 0..1,
        or ``slow_ms`` is not a range of non-negative times.

    Notes
    -----
    Varies the datasheet's "Timing": "Modbus RTU answers within 5 ms, TCP within 10 ms on
    a quiet network, ASCII within 10 ms. A host should treat 100 ms without an answer as
    a timeout."
    """

    min_ms: float = 0.5
    max_ms: float | None = None
    slow_fraction: float = 0.0
    slow_ms: tuple[float, float] = (50.0, 90.0)

    def __post_init__(self) -> None:
        hi = self.max_ms if self.max_ms is not None else self.min_ms
        if not 0 <= self.min_ms <= hi:
            raise ValueError(f"latency: need 0 <= min_ms <= max_ms, got {self.min_ms}, {hi}")
        if not 0 <= self.slow_fraction <= 1:
            raise ValueError(f"latency: slow_fraction {self.slow_fraction} outside 0..1")
        lo_s, hi_s = self.slow_ms
        if not 0 <= lo_s <= hi_s:
            raise ValueError(f"latency: slow_ms {self.slow_ms} is not a range")

    def draw_s(self, rng: np.random.Generator, transport: str) -> float:
        """One answer's delay.

        Parameters
        ----------
        rng : numpy.random.Generator
            The stream to draw from (one or two draws per answer).
        transport : str
            ``"modbus-tcp"``, ``"modbus-rtu"`` or ``"ascii"``: the datasheet's bound when
            ``max_ms`` is None.

        Returns
        -------
        float
            The delay, s.

        Raises
        ------
        KeyError
            If ``max_ms`` is None and ``transport`` is not one of the three.
        """
        if self.slow_fraction and rng.random() < self.slow_fraction:
            return float(rng.uniform(*self.slow_ms)) / 1000
        hi = self.max_ms if self.max_ms is not None else DATASHEET_LATENCY_MS[transport]
        return float(rng.uniform(self.min_ms, max(hi, self.min_ms))) / 1000

    @classmethod
    def parse(cls, text: str, slow_fraction: float = 0.0) -> Latency:
        """A latency from ``loopcal simulate --latency``'s text.

        Parameters
        ----------
        text : str
            ``datasheet`` (0.5 ms to the transport's bound), ``MS`` (always that long) or
            ``MIN-MAX`` (uniform between), in ms, e.g. ``"2-8"``.
        slow_fraction : float, default 0.0
            Probability of a slow answer (50-90 ms; ``--slow-answers``).

        Returns
        -------
        Latency

        Raises
        ------
        ValueError
            If ``text`` is none of those forms, or the values are out of range.
        """
        m = _LATENCY.match(text.strip())
        if not m:
            raise ValueError(f"latency {text!r}: give 'datasheet', MS or MIN-MAX (ms)")
        if m["ds"]:
            return cls(slow_fraction=slow_fraction)
        lo = float(m["lo"])
        hi = float(m["hi"]) if m["hi"] else lo
        return cls(min_ms=lo, max_ms=hi, slow_fraction=slow_fraction)


@dataclass(frozen=True)
class OpenPoints:
    """The emulated module's choices where the datasheet leaves room.

    Every default is what the emulator did before it had the setting: ``OpenPoints()`` is
    the emulator as it always was. The module docstring, and docs/daq.md, say what each
    setting varies; :data:`DATASHEET_LINES` names the datasheet line.

    Attributes
    ----------
    scan_phase_us : int, default 0
        Device time of scan 0 after power-on, µs, 0..1000000 (the module answers nothing
        before it). Varies "Every scan gets a 32-bit scan counter (starts at 0 at
        power-on ...)": not when scan 0 is taken.
    clock_ppm : float, default 0.0
        The module's clock error against the host's, parts per million, -10000..10000
        (+200: a 20 Hz module scans at 20.004 Hz by the host's clock, and its device time
        runs 200 ppm fast). Varies "The module scans on its own clock".
    latency : Latency or None, default None
        How long answers take (None: sent at once). Varies the datasheet's answer times.
    fifo_underrun : {"filler", "short"}, default "filler"
        A FIFO read asking for more scans than are waiting: the waiting scans then
        all-0xFFFF filler scans, or only the waiting ones (a shorter answer). Varies
        "asking for more scans than are waiting returns the waiting ones followed by
        all-0xFFFF filler scans".
    max_read_registers : int, default 125
        Registers one read may ask for, 1..125 (Modbus' own limit,
        :data:`MODBUS_MAX_READ`). Varies "N is at most 20 per request".
    over_limit : {"refuse", "truncate"}, default "refuse"
        A read of more than ``max_read_registers``: exception 03, or an answer of its
        first ``max_read_registers`` registers (whole scans in the FIFO window, the rest
        left waiting).
    holes : {"refuse", "zero"}, default "refuse"
        A read that leaves the listed input registers (0-9, 256-375, 512-515): exception
        02, or 0 for the unlisted ones. Varies the input register table, which lists those
        blocks only.
    snapshot_reads : {"any", "whole"}, default "any"
        Reads of part of registers 0..9: answered, or refused with 02 (only 0..9 at once).
        Varies "A single read of registers 0..9 is one consistent snapshot".

    Raises
    ------
    ValueError
        If a setting is out of its range or not one of its choices.
    """

    scan_phase_us: int = 0
    clock_ppm: float = 0.0
    latency: Latency | None = None
    fifo_underrun: Literal["filler", "short"] = "filler"
    max_read_registers: int = MODBUS_MAX_READ
    over_limit: Literal["refuse", "truncate"] = "refuse"
    holes: Literal["refuse", "zero"] = "refuse"
    snapshot_reads: Literal["any", "whole"] = "any"

    def __post_init__(self) -> None:
        if not 0 <= self.scan_phase_us <= 1_000_000:
            raise ValueError(f"scan_phase_us {self.scan_phase_us} outside 0..1000000")
        if not abs(self.clock_ppm) <= 10_000:
            raise ValueError(f"clock_ppm {self.clock_ppm} outside -10000..10000")
        if self.fifo_underrun not in ("filler", "short"):
            raise ValueError(f"fifo_underrun {self.fifo_underrun!r}: 'filler' or 'short'")
        if not 1 <= self.max_read_registers <= MODBUS_MAX_READ:
            raise ValueError(f"max_read_registers {self.max_read_registers} outside 1..125")
        if self.over_limit not in ("refuse", "truncate"):
            raise ValueError(f"over_limit {self.over_limit!r}: 'refuse' or 'truncate'")
        if self.holes not in ("refuse", "zero"):
            raise ValueError(f"holes {self.holes!r}: 'refuse' or 'zero'")
        if self.snapshot_reads not in ("any", "whole"):
            raise ValueError(f"snapshot_reads {self.snapshot_reads!r}: 'any' or 'whole'")

    def changed(self) -> dict[str, object]:
        """The settings that differ from the defaults (for logs and truth headers).

        Returns
        -------
        dict of str to object
            ``{field name: value}`` of each setting not at its default; empty for
            ``OpenPoints()``.
        """
        default = OpenPoints()
        return {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if getattr(self, f.name) != getattr(default, f.name)
        }


#: The datasheet line each setting varies.
DATASHEET_LINES = {
    "scan_phase_us": "Scanning: the counter 'starts at 0 at power-on' (not when scan 0 is taken)",
    "clock_ppm": "Scanning: 'The module scans on its own clock' (not how accurate it is)",
    "latency": "Timing: 'RTU answers within 5 ms, TCP within 10 ms, ASCII within 10 ms'",
    "fifo_underrun": "Input register 256..: 'asking for more scans than are waiting ...'",
    "max_read_registers": "Input register 256..: 'N is at most 20 per request'",
    "over_limit": "Input register 256..: 'N is at most 20 per request'",
    "holes": "Input registers: only 0-9, 256.. and 512-515 are listed",
    "snapshot_reads": "'A single read of registers 0..9 is one consistent snapshot'",
}


def add_arguments(p: argparse.ArgumentParser, *, scanning: bool = True) -> None:
    """Add the ``loopcal simulate`` options for :class:`OpenPoints` to a parser.

    Defaults: the datasheet's most literal reading, what the emulator always did. The
    options go in an argument group of their own: ``--scan-phase-us``, ``--clock-ppm``,
    ``--latency``, ``--slow-answers``, ``--fifo-underrun``, ``--max-read-registers``,
    ``--over-limit``, ``--holes``, ``--snapshot-reads``.

    Parameters
    ----------
    p : argparse.ArgumentParser
        The parser to add them to.
    scanning : bool, default True
        False leaves out when and how fast the module scans (``--scan-phase-us``,
        ``--clock-ppm``; a replay serves the recorded times): only how it answers.
    """
    g = p.add_argument_group(
        "what the datasheet leaves open (docs/daq.md; defaults: the emulator as it was)"
    )
    if scanning:
        g.add_argument("--scan-phase-us", type=int, default=0, metavar="US",
                       help="device time of scan 0 after power-on, us (0)")  # fmt: skip
        g.add_argument("--clock-ppm", type=float, default=0.0, metavar="PPM",
                       help="the module's clock error against the host's, ppm (0)")  # fmt: skip
    g.add_argument("--latency", default=None, metavar="datasheet|MS|MIN-MAX",
                   help="answer delay, ms ('datasheet': 0.5 ms to 5 ms RTU, 10 ms TCP and "
                        "ASCII; default: at once)")  # fmt: skip
    g.add_argument("--slow-answers", type=float, default=0.0, metavar="FRACTION",
                   help="with --latency: this fraction of answers takes 50-90 ms (0)")  # fmt: skip
    g.add_argument("--fifo-underrun", choices=("filler", "short"), default="filler",
                   help="a FIFO read asking more scans than wait: 0xFFFF filler scans, or "
                        "only the waiting scans (default filler)")  # fmt: skip
    g.add_argument("--max-read-registers", type=int, default=MODBUS_MAX_READ, metavar="N",
                   help="registers one read may ask for (125)")  # fmt: skip
    g.add_argument("--over-limit", choices=("refuse", "truncate"), default="refuse",
                   help="a longer read: exception 03, or its first N registers")  # fmt: skip
    g.add_argument("--holes", choices=("refuse", "zero"), default="refuse",
                   help="a read over unlisted input registers: exception 02, or 0")  # fmt: skip
    g.add_argument("--snapshot-reads", choices=("any", "whole"), default="any",
                   help="reads of part of registers 0..9: answered, or refused (any)")  # fmt: skip


def from_arguments(args: argparse.Namespace) -> OpenPoints:
    """The :class:`OpenPoints` the options :func:`add_arguments` added ask for.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed arguments (without ``--scan-phase-us`` and ``--clock-ppm`` when added with
        ``scanning=False``: those are then left at their defaults).

    Returns
    -------
    OpenPoints

    Raises
    ------
    ValueError
        If ``--slow-answers`` is given without ``--latency``, or a value is out of range;
        the message starts with the option, as the user typed it (``--latency: ...``).
    """
    if args.slow_answers and args.latency is None:
        raise ValueError("--slow-answers needs --latency")
    try:
        latency = None if args.latency is None else Latency.parse(args.latency, args.slow_answers)
        return OpenPoints(
            scan_phase_us=getattr(args, "scan_phase_us", 0),
            clock_ppm=getattr(args, "clock_ppm", 0.0),
            latency=latency,
            fifo_underrun=args.fifo_underrun,
            max_read_registers=args.max_read_registers,
            over_limit=args.over_limit,
            holes=args.holes,
            snapshot_reads=args.snapshot_reads,
        )
    except ValueError as exc:  # named by the option, as the user typed it
        setting = str(exc).split()[0].rstrip(":")
        raise ValueError(f"--{setting.replace('_', '-')}: {exc}") from None
