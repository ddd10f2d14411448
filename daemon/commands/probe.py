"""``loopcal probe URL [--json] [--timeout D]``: is the LDQ-412 there, and what is it.

Within 5 s whatever is wrong, it says either what answers at the URL (model, firmware,
serial number, scan rate, FIFO level and overflow flag, restart flag, the latest scan's
four codes and volts, the round trip of its answers) or why nothing does: nothing listens
at the address, the host does not answer, something answers that is not Modbus or not the
module, the unit id or ASCII address is not the module's (the others are tried, the
datasheet's defaults first, and the one that answers is named with the URL to use), no
such serial device (the ports there are, listed), permission denied on it (its group,
and whether you are in it), the device or module held by another process (its pid), or a
line rate that is not the module's (the usual rates are tried, and the one that answers
named). The module is only read: nothing on it is changed and no scan taken off its FIFO.

A module that a ``loopcal record`` or the service records is not probed: the recorder owns
it, and its log says every 30 s why it cannot reach it (docs/daemon.md). ``--json`` prints
one object (``found``, ``cause``, ``message``, ``hint``, ``identity``, ``module``,
``rtt_ms``, ``tried``, ...; docs/hardware.md). Exit status: 0 the module answers at the URL,
1 it does not (the cause is said), 2 a bad URL or option.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from typing import TYPE_CHECKING

from ..arguments import duration_argument
from .errors import CommandError

if TYPE_CHECKING:  # the command's module imports no driver until it runs
    from loopcal.drivers.probe import ProbeReport

#: the longest --timeout, s: a module slower than this is not working, and five tries fit
MAX_TIMEOUT_S = 1.0
#: tries listed by the text output (--json lists all)
SHOWN_TRIES = 8


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("url", metavar="URL",
                   help="the DAQ's driver URL, as loopcal record --daq takes it, e.g. "
                        "modbus-tcp://192.168.1.50:502?unit=1 or "
                        "modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1")  # fmt: skip
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--timeout", type=duration_argument, metavar="D",
                   help="how long to wait for each answer (default: the datasheet's 0.1 s; "
                        f"at most {MAX_TIMEOUT_S:g}): more for a slow network, each other "
                        "setting tried then costs as much")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from loopcal.drivers import driver_for_url
    from loopcal.drivers.diagnosis import Diagnosis
    from loopcal.drivers.probe import ProbeReport, probe

    from ..recorder.ownership import ModuleHeld, ModuleLock

    try:
        driver_for_url(args.url)
    except ValueError as exc:
        raise CommandError(exc) from None
    if args.timeout is not None and args.timeout > MAX_TIMEOUT_S:
        raise CommandError(f"--timeout {args.timeout:g} s: at most {MAX_TIMEOUT_S:g} s (a "
                           "module that slow is not working)")  # fmt: skip
    # pymodbus logs an ERROR line for each try that gets no answer: the report says it
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL + 1)
    start = time.monotonic()
    try:  # held while probing: no recorder starts on the module meanwhile
        lock = ModuleLock(args.url, command=f"loopcal probe {args.url}")
    except ModuleHeld as exc:
        if exc.holder is None:  # no lock to take (a runtime directory we may not use)
            lock = None
        else:
            holder = exc.holder
            stop = "systemctl stop loopcal" if holder.service else f"kill {holder.pid}"
            held = Diagnosis(
                "busy", f"the module at {args.url} is recorded by {holder.describe()}: it owns "
                "the module, and is not disturbed",
                "its log says every 30 s why it cannot reach the module, and its status line "
                f"whether it does (systemctl status loopcal); to probe, stop it first ({stop})",
                {"holder": holder.__dict__})  # fmt: skip
            report = ProbeReport.of(args.url, held, elapsed_s=round(time.monotonic() - start, 4))
            return _print(report, args.json)
    try:
        kw = {} if args.timeout is None else {"timeout": args.timeout}
        report = probe(args.url, **kw)
    finally:
        if lock is not None:
            lock.release()
    return _print(report, args.json)


def _print(report: ProbeReport, as_json: bool) -> int:
    """Print the report; the exit status (0 found, 1 a cause)."""
    if as_json:
        print(json.dumps(report.to_json(), indent=1))
        return 0 if report.found else 1
    print(("found: " if report.found else f"not found [{report.cause}]: ") + report.message)
    if report.identity is not None and report.module is not None:
        _print_module(report)
    for note in report.notes:
        print(f"  note: {note}")
    if report.hint:
        print(f"hint: {report.hint}")
    if not report.found and report.tried:
        print(f"tried ({len(report.tried)}):")
        for attempt in report.tried[:SHOWN_TRIES]:
            print(f"  {attempt.url}: {attempt.outcome} ({attempt.elapsed_s:.2f} s)")
        if len(report.tried) > SHOWN_TRIES:
            print(f"  ... {len(report.tried) - SHOWN_TRIES} more (--json lists them)")
    print(f"probed in {report.elapsed_s:.2f} s (budget {report.budget_s:g} s, "
          f"{report.timeout_s:g} s for each answer)")  # fmt: skip
    return 0 if report.found else 1


def _print_module(report: ProbeReport) -> None:
    ident, module, rtt = report.identity, report.module, report.rtt_ms
    serial = ident["serial"]
    number = "" if serial is None else f", serial {serial} ({serial:#010x})"
    scan = module["scan"]
    fifo = "no FIFO over ASCII" if module["fifo_level"] is None else \
        f"{module['fifo_level']} scans waiting"  # fmt: skip
    volts = " ".join(f"{v:+.3f}" for v in scan["volts"])
    print(f"  model         {ident['model']} firmware {ident['firmware']}{number}")
    print(f"  at            {report.answered_url}")
    print(f"  scan rate     {module['scan_rate_hz']} Hz")
    overflow = "set: scans were lost while nobody read them" if module["overflow"] else "clear"
    restarted = "set: powered on since a recorder last cleared it" if module["restarted"] \
        else "clear"  # fmt: skip
    print(f"  FIFO          {fifo}; overflow flag {overflow}")
    print(f"  restart flag  {restarted}")
    print(f"  latest scan   counter {scan['counter']}: codes "
          f"{' '.join(map(str, scan['codes']))} = {volts} V")  # fmt: skip
    print(f"  round trip    median {rtt['median']:.1f} ms, max {rtt['max']:.1f} ms "
          f"({rtt['n']} answers)")  # fmt: skip
