"""``loopcal simulate``'s command line, and the options every command that serves an
emulated module shares (``simulate``, ``replay``, ``demo``): :func:`add_arguments`,
:func:`add_transport_option` and the argparse types :func:`listen_host`, :func:`tcp_port`
and :func:`int_in`.

Nothing here serves or simulates (no numpy, no pymodbus): a command's ``--help`` builds its
parser from this module at once, and the serving, :mod:`loopcal.simulator.run`, is imported
only to run.
"""

from __future__ import annotations

import argparse
import math
import socket
from collections.abc import Callable
from pathlib import Path

from .choices import LINES, SCENARIO_NAMES, TRANSPORTS
from .open_points import add_arguments as add_open_point_arguments
from .options import add_simulation_options

#: ``loopcal simulate``'s description: its ``--help``, and what ``--help-faults`` prints
DESCRIPTION = """\
``loopcal simulate``: serve an emulated LDQ-412 driven by a simulated shoulder joint.

Prints where it listens (the driver URL; for serial transports the pseudo-terminal path a
driver opens like /dev/ttyUSB0), applies scheduled faults, and can stream its ground truth
(the true parameters, then every scan it produced with the plate's true orientation) to a
JSON Lines file.

Fault schedule, times in seconds of device time since start (repeatable ``--fault``)::

    restart@30            power cycle at 30 s (2 s off)
    stall@12+2            no answers from 12 s for 2 s
    disconnect@20+3       link down from 20 s for 3 s
    garbage@8:16          16 junk bytes before the next answer at 8 s
    corrupt@10:3          the next 3 answers with a broken CRC/checksum/MBAP
    stuck@15+5:2=1000     channel 2 stuck at code 1000 from 15 s for 5 s
    sensor@15+5:3         sensor fault on channel 3 from 15 s for 5 s
    saturate@15+5:1=high  channel 1 at the high rail from 15 s for 5 s
    offset@30:3=+0.5      sensor 3's offset steps by +0.5 mm at 30 s (held; +DUR: for DUR s)
    creep@30:2=1.0        sensor 2's offset creeps by 1.0 mm per minute from 30 s
                          (for ever; +DUR: for DUR s, then held)
"""


def speed_argument(text: str) -> float:
    """An argparse type: an emulated module's speed.

    Parameters
    ----------
    text : str
        The option's value as typed.

    Returns
    -------
    float
        A finite number above 0: the module's clock runs that many times as fast as the
        wall clock.

    Raises
    ------
    argparse.ArgumentTypeError
        For text that is not such a number.
    """
    try:
        speed = float(text)
    except ValueError:
        speed = math.nan
    if not (math.isfinite(speed) and speed > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: a speed must be a number above 0")
    return speed


def add_speed_option(p: argparse.ArgumentParser, default: float | None = 1.0,
                     shown: str = "1") -> None:  # fmt: skip
    """Add ``--speed X``: how many times as fast as the wall clock the emulated module's
    clock runs (``loopcal simulate``, ``replay`` and ``demo``).

    Parameters
    ----------
    p : argparse.ArgumentParser
        The command's parser.
    default : float or None, default 1.0
        The value without the option (None: the command decides, by other options).
    shown : str, default "1"
        The default as its help says it.
    """
    p.add_argument("--speed", type=speed_argument, default=default, metavar="X",
                   help="the emulated module's seconds per wall-clock second "
                        f"(default {shown})")  # fmt: skip


def int_in(lo: int, hi: int, *, base: int = 10) -> Callable[[str], int]:
    """An argparse type: an integer in lo..hi (hexadecimal digits with base 16).

    Parameters
    ----------
    lo, hi : int
        The range, both included.
    base : int, default 10
        10 (decimal, a leading ``-`` allowed) or 16 (hexadecimal digits, no sign, no
        ``0x``).

    Returns
    -------
    callable
        ``parse(text) -> int``, raising :class:`argparse.ArgumentTypeError` for text
        that is not such an integer or is outside lo..hi.
    """

    def parse(text: str) -> int:
        digits = "0123456789abcdefABCDEF"[: 10 if base == 10 else 22]
        if not text or not all(c in digits for c in text.lstrip("-" if base == 10 else "")):
            kind = "hexadecimal digits" if base == 16 else "an integer"
            raise argparse.ArgumentTypeError(f"{text!r} is not {kind}")
        value = int(text, base)
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{text} is outside {lo}..{hi}")
        return value

    return parse


#: a TCP port to listen on, 0 for a free one
tcp_port = int_in(0, 65535)


def listen_host(text: str) -> str:
    """An argparse type: an address (or name) this machine can listen on.

    Parameters
    ----------
    text : str
        An address or host name.

    Returns
    -------
    str
        ``text``, if :func:`socket.getaddrinfo` resolves it.

    Raises
    ------
    argparse.ArgumentTypeError
        If it does not resolve.
    """
    try:
        socket.getaddrinfo(text, None, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise argparse.ArgumentTypeError(f"{text!r} is not an address: {exc}") from None
    return text


def add_transport_option(p: argparse.ArgumentParser, what: str) -> None:
    """Add ``--transport`` and ``--line`` to a command that serves an emulated module
    (simulate, replay, demo).

    Parameters
    ----------
    p : argparse.ArgumentParser
        The command's parser.
    what : str
        What goes over the wire, for the option's help (the choices and the default,
        modbus-tcp, follow it).
    """
    p.add_argument("--transport", choices=TRANSPORTS, default="modbus-tcp",
                   help=f"{what}: {', '.join(TRANSPORTS)} (default modbus-tcp)")  # fmt: skip
    p.add_argument("--line", choices=LINES, default=LINES[0],
                   help="a serial transport's line: pty (a pseudo-terminal a driver opens "
                        "like /dev/ttyUSB0) or tcp (raw TCP through a serial device server "
                        f"on the listening address) (default {LINES[0]})")  # fmt: skip


def add_arguments(p: argparse.ArgumentParser, duration: Callable[[str], float] = float) -> None:
    """Add ``loopcal simulate``'s options to its parser.

    The transport and listening address, the module's identity and power-on settings, the
    speed, the simulated mechanism (scenario, the task loop, true parameters; the seed,
    noise, pauses, twists and offset error of :mod:`loopcal.simulator.options`), the fault
    schedule, the duration, the truth file, and the open points
    (:func:`~loopcal.simulator.open_points.add_arguments`).

    Parameters
    ----------
    p : argparse.ArgumentParser
        The ``simulate`` command's parser.
    duration : callable
        The type of ``--duration``: text to s (``loopcal simulate`` passes the command
        line's one duration syntax, ``90``, ``90s``, ``15m``).
    """
    add_transport_option(p, "the wire the emulated module answers on")
    p.add_argument(
        "--host", type=listen_host, default="127.0.0.1", help="TCP address (default 127.0.0.1)"
    )
    p.add_argument("--port", type=tcp_port, default=0, help="TCP port (default: a free one)")
    p.add_argument("--unit", type=int_in(1, 247), default=1, help="Modbus unit id (default 1)")
    p.add_argument(
        "--addr", type=int_in(0, 0xFF, base=16), default=1, help="ASCII address, hex (01)"
    )
    p.add_argument("--checksum", action="store_true", help="ASCII checksum mode on at power-on")
    p.add_argument(
        "--scan-rate", type=int_in(1, 200), default=20, help="scan rate at power-on, Hz (20)"
    )
    add_speed_option(p)
    p.add_argument(
        "--wait-for-client",
        action="store_true",
        help="switch the module on at a client's first request (default: at once)",
    )
    p.add_argument("--scenario", choices=(*SCENARIO_NAMES, "replay"), default="hand",
                   help="how the plate moves: hand (a technician, pausing), static, sweep, "
                        "task (the controller's task loop, for ever), or replay (a "
                        "--truth-out file; default hand)")  # fmt: skip
    p.add_argument(
        "--replay",
        type=Path,
        default=None,
        help="with --scenario replay: a --truth-out file to play back (loops)",
    )
    add_simulation_options(p, what="with --scenario hand: ")
    p.add_argument(
        "--task-waypoints",
        type=int,
        default=None,
        metavar="N",
        help="with --scenario task: the loop's waypoints, fixed orientations drawn from the "
        "seed, 2 or more (default 5)",
    )
    p.add_argument(
        "--task-move",
        type=float,
        default=None,
        metavar="S",
        help="with --scenario task: seconds of each move between two waypoints (default 2)",
    )
    p.add_argument(
        "--task-dwell",
        type=float,
        default=None,
        metavar="S",
        help="with --scenario task: seconds the plate stays at each waypoint, 0 for none "
        "(default 0.5)",
    )
    p.add_argument("--truth", default=None, help="true parameters, e.g. 'd01=99.1,A1x=68.9'")
    p.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="SPEC",
        help="schedule a fault (see loopcal simulate --help-faults)",
    )
    p.add_argument("--help-faults", action="store_true", help="explain the fault syntax")
    p.add_argument(
        "--duration",
        type=duration,
        default=None,
        metavar="D",
        help="stop after this long by the module's clock (device time: at --speed X, 1/X of "
        "it in wall time): seconds, or 90s, 15m, 2h (default: until a signal)",
    )
    p.add_argument(
        "--truth-out", type=Path, default=None, help="write the ground truth here (JSON Lines)"
    )
    add_open_point_arguments(p)
