"""``loopcal session --config DAEMON.toml``: calibrate through the running daemon, for the
technician after a sensor replacement.

The daemon owns the module, so this command does not open it: it asks the daemon, over its
control socket (``[control].socket``), to start a session. The daemon writes the session
into its recording and streams its live guidance from its own scans (what has been
collected, the predicted precision, which way to tilt and twist next), shown here as
``loopcal record --until-enough`` shows it. The session stops once the recording is enough
(with ``--until-enough``), after ``--duration`` (of the module's scans), or at Ctrl-C.
Then exactly the session's window of the daemon's recording (flushed to disk up to its
last scan) is calibrated as ``loopcal calibrate`` does it: the same worker, gates and
output; with ``--write`` and every gate passed, the controller config the daemon records
with is written through the same durable path, and the daemon follows it within seconds.

Exit status as ``loopcal calibrate``: 0 accepted (and written with ``--write``), 1 a gate
refused it (nothing written), 2 bad input, no daemon, or a session already running.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import time
from types import FrameType
from typing import Any

from loopcal.calibration.errors import ParameterError

from ..arguments import duration_argument, path_argument
from ..live.control import MAX_NOTE_CHARS, ControlClient
from ..times import time_text
from .calibrate import Calibration, calibrate, check_report_dir
from .errors import CommandError
from .guidance_display import Display, add_guidance_options, target_mm

#: s between two messages to the daemon: it abandons a session whose client is silent for
#: ``[control].client_timeout`` (30 s by default)
HEARTBEAT_S = 2.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", required=True, type=path_argument, metavar="DAEMON.toml",
                   help="the running daemon's config (its control socket, recording "
                        "directory and controller config), e.g. "
                        "/etc/loopcal/daemon.toml")  # fmt: skip
    add_guidance_options(p, until_enough="stop by itself once the recording calibrates well "
                                         "enough")  # fmt: skip
    p.add_argument("--duration", type=duration_argument, metavar="D",
                   help="stop after this much of the module's scans: seconds, or 90s, 5m "
                        "(the module's clock: a real module's is the wall clock)")  # fmt: skip
    p.add_argument("--free", metavar="NAMES",
                   help="free parameters, as loopcal calibrate takes them (default: the "
                        "controller config's [calibration].free, else paper7)")  # fmt: skip
    p.add_argument("--note", default="", metavar="TEXT",
                   help="a note recorded with the session, e.g. 'sensor 3 replaced'")  # fmt: skip
    p.add_argument("--write", action="store_true",
                   help="write the new values into the controller config if every gate "
                        "passes")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help="JSON lines on stdout: one object per guidance update, then the "
                        "calibration's result on one line (its \"session\": the "
                        "session)")  # fmt: skip
    p.add_argument("--report", type=path_argument, metavar="DIR",
                   help="write an HTML report with plots into DIR")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    job, client = _prepare(args)
    with client:
        ended = _follow(client, args)
    return calibrate(_window(job, ended))


def _prepare(args: argparse.Namespace) -> tuple[Calibration, ControlClient]:
    """Everything checked before the daemon is asked: the daemon's config, the controller
    config (writable, with --write), the report's directory, the options."""
    from loopcal.calibration.parameters import ParameterModel

    from ..config.controller import load_controller_config
    from ..recorder.settings import load_daemon_config
    from ..worker.writeback import check_writable

    if len(args.note) > MAX_NOTE_CHARS:
        raise CommandError(f"--note: at most {MAX_NOTE_CHARS} characters")
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in args.note):
        raise CommandError("--note: control characters (a newline, say) are not taken")
    settings = load_daemon_config(args.config)
    if settings.controller_config is None:
        raise CommandError(f"{args.config}: no [controller].config: a session calibrates the "
                           "controller config the daemon records with")  # fmt: skip
    config = load_controller_config(settings.controller_config)
    if args.write:
        check_writable(config)
    if args.free is not None:
        try:
            ParameterModel.parse(args.free, ())
        except ParameterError as exc:
            raise CommandError(f"--free: {exc}") from None
    if args.report is not None:
        check_report_dir(args.report)
    assert settings.control_socket is not None
    client = ControlClient(settings.control_socket)
    job = Calibration([settings.directory], settings.controller_config, free=args.free,
                      write=args.write, json=args.json, report=args.report,
                      json_indent=None)  # fmt: skip
    return job, client


def _follow(client: ControlClient, args: argparse.Namespace) -> dict[str, Any]:
    """Start the session, show its guidance until it ends, and return its end."""
    client.send("start", note=args.note,
                target_mm=target_mm(args),
                until_enough=args.until_enough, duration_s=args.duration,
                free=args.free)  # fmt: skip
    reply = client.receive(timeout=10.0)
    if reply is None:
        raise CommandError(f"the daemon at {client.path} did not answer within 10 s")
    if reply.get("type") != "started":
        raise CommandError(f"the daemon refused the session: {reply.get('error', reply)}")
    session = reply["session"]
    say = _say(args.json)
    say(f"session {session['id']} started through the daemon: move the plate as the guidance "
        "says; Ctrl-C ends the session and calibrates what it recorded")  # fmt: skip
    display = Display(json_lines=args.json)
    asked: list[int] = []

    def interrupt(signum: int, frame: FrameType | None) -> None:
        if asked:  # a second Ctrl-C: leave at once (the daemon ends the session itself)
            raise KeyboardInterrupt
        asked.append(signum)

    previous = signal.signal(signal.SIGINT, interrupt)
    try:
        sent = 0.0
        stop_sent = False
        while True:
            if asked and not stop_sent:
                client.send("stop")
                stop_sent = True
                say("stopping the session ...")
            if time.monotonic() - sent >= HEARTBEAT_S:
                client.send("status")
                sent = time.monotonic()
            msg = client.receive(timeout=0.25)
            if msg is None:
                continue
            kind = msg.get("type")
            if kind == "guidance":
                if args.json:
                    print(json.dumps(msg["update"]), flush=True)
                else:
                    display.lines(list(msg["lines"]))
            elif kind == "ended":
                return _ended(msg["session"], say)
            elif kind == "error":
                say(f"the daemon says: {msg.get('error')}")
    except KeyboardInterrupt:
        raise CommandError("interrupted twice: the session was left to the daemon, which ends it "
                           "as abandoned; nothing calibrated") from None  # fmt: skip
    finally:
        signal.signal(signal.SIGINT, previous)


def _say(json_lines: bool):
    def say(text: str) -> None:
        print(text, file=sys.stderr if json_lines else sys.stdout, flush=True)

    return say


def _ended(session: dict[str, Any], say) -> dict[str, Any]:
    """Say how the session ended; refuse to calibrate what did not reach the disk."""
    why = f" ({session['why']})" if session.get("why") else ""
    say(f"session {session['id']} ended: {session['reason']}{why}; "
        f"{session.get('scans', 0):,} scans")  # fmt: skip
    if session.get("since_ns") is None:
        raise CommandError("the session saw no scan: is the module connected? (`systemctl status "
                           "loopcal` shows the daemon's state)")  # fmt: skip
    if not session.get("flushed"):
        why = session.get("flush_error", "unknown")
        raise CommandError(f"the daemon could not write the session's scans to disk: {why}; "
                           "nothing calibrated")
    return session


def _window(job: Calibration, session: dict[str, Any]) -> Calibration:
    """The calibration of exactly the session's scans (its first to its last stamp)."""
    from dataclasses import replace

    since, until = int(session["since_ns"]), int(session["until_ns"])
    session = {**session, "since": time_text(since), "until": time_text(until)}
    return replace(job, since_ns=since, until_ns=until + 1, extra={"session": session})
