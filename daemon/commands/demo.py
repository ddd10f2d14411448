"""``loopcal demo``: the field job for real, on the built-in emulated DAQ.

A simulated shoulder joint whose LVDTs were refitted (offsets lost, known only to the
simulation) is moved by a technician's hand for 75 seconds as the guidance asks, tilting it
and, every other move, twisting it about its own axis (every scan counts, moving or
still: the hand pauses about a second between moves only as people do). Its
emulated LDQ-412 is recorded by ``loopcal record`` through a real driver over a real
transport; ``loopcal calibrate --write`` turns the recording into new values in a fresh
controller config (``loopcal init-config``); and what was written is compared with the truth.
The emulated module runs ``--speed`` times as fast as wall time, so 75 s of session take
about eight seconds (over ASCII, which polls, in real time: progress is shown).

Each command is shown as it is run, quoted to paste into a shell. The end says where the
files are (the recording, the controller config, the HTML report): in ``--out DIR``, or in
a temporary directory that is removed unless ``--keep``. The last line is the verdict:
written (and how close to the truth), or refused and why, nothing written.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from loopcal.calibration.defaults import DEFAULT_METHOD, METHODS
from loopcal.simulator.arguments import add_speed_option, add_transport_option
from loopcal.simulator.options import add_simulation_options, check_simulation_options

from ..arguments import duration_argument, path_argument
from .errors import CommandError
from .model_options import add_model_options, model_from_args

if TYPE_CHECKING:  # the simulation, the emulator and the config (numpy, pymodbus): imported
    import numpy as np  # by the demo when it runs

    from loopcal.calibration.parameters import ParameterModel
    from loopcal.simulator import Emulator
    from loopcal.simulator.clock import HeldClock

    from ..config.controller import ControllerConfig

PROGRESS_S = 5.0  # wall seconds between progress lines while recording
SESSION_S = 75.0  # the session, s of the emulated module's time


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_transport_option(p, "the wire between the recorder and the emulated module")
    p.add_argument("--duration", type=duration_argument, default=SESSION_S, metavar="D",
                   help="the session's length by the emulated module's clock (at --speed X, "
                        f"1/X of it in wall time): seconds, or 90s, 2m (default {SESSION_S:g} "
                        "s)")  # fmt: skip
    add_speed_option(p, default=None, shown="10; 1 over ASCII, which polls")
    add_simulation_options(p)
    add_model_options(p)
    p.add_argument(
        "--method",
        choices=METHODS,
        default=DEFAULT_METHOD,
        help=f"estimator for loopcal calibrate (default {DEFAULT_METHOD})",
    )
    p.add_argument(
        "--out",
        type=path_argument,
        default=None,
        metavar="DIR",
        help="keep the recording, config and report here (default: a temporary directory, "
        "removed at the end unless --keep)",
    )
    p.add_argument("--keep", action="store_true",
                   help="keep the temporary directory (without --out)")  # fmt: skip
    p.add_argument("--json", action="store_true",
                   help="one JSON object on stdout at the end (verdict, what was written "
                        "against the truth); the session's output goes to stderr")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    if not args.json:
        return _run(args, {})
    report: dict[str, Any] = {}
    with contextlib.redirect_stdout(sys.stderr):  # the commands' output too (_start)
        status = _run(args, report)
    print(json.dumps({"exit_status": status, **report}, indent=1))
    return status


def _run(args: argparse.Namespace, report: dict[str, Any]) -> int:
    """The demo; ``report`` gets what --json prints: verdict, written, work, parameters."""
    try:
        check_simulation_options(args)
    except ValueError as exc:  # the option and its value, named
        raise CommandError(exc) from None
    speed = args.speed if args.speed is not None else (1.0 if args.transport == "ascii" else 10.0)
    model = model_from_args(args)
    if args.out is None:
        work = Path(tempfile.mkdtemp(prefix="loopcal-demo-"))
        try:
            return _in(work, args, model, speed, report)
        finally:
            if not args.keep:
                shutil.rmtree(work, ignore_errors=True)
    else:
        work = args.out
        if work.exists() and not work.is_dir():
            raise CommandError(f"--out {work}: exists and is not a directory")
        try:
            work.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CommandError(f"--out {work}: cannot create it: {exc.strerror or exc}") from None
        return _in(work, args, model, speed, report)


def _in(work: Path, args: argparse.Namespace, model: ParameterModel, speed: float,
        report: dict[str, Any]) -> int:  # fmt: skip
    """The demo working in ``work``."""
    import numpy as np

    from loopcal.calibration.simulate import perturbed_truth
    from loopcal.simulator import Emulator
    from loopcal.simulator.clock import HeldClock
    from loopcal.simulator.mechanism import MechanismSource
    from loopcal.simulator.scenarios import HandMoves

    from ..config.controller import load_controller_config

    kept = args.out is not None or args.keep
    report.update(work=str(work), kept=kept, written=False, parameters={})
    t_start = time.perf_counter()
    truth = perturbed_truth(
        np.random.default_rng(args.seed), offsets_mm=args.offset_error, model=model
    )
    print(
        f"A shoulder joint whose LVDTs were refitted (offsets off by up to "
        f"{args.offset_error:g} mm), {args.noise_mv:g} mV of sensor noise; a technician moves "
        f"it by hand for {args.duration:g} s"
        + (f", twisting it every {args.twist_every} moves" if args.twist_every else "")
        + f". Working in {work}."
    )
    source = MechanismSource(
        HandMoves(args.seed, params=truth, pause_s=args.pause, twist_every=args.twist_every),
        truth,
        noise_volts=args.noise_mv / 1000,
        seed=args.seed,
    )
    recordings = work / "recordings"
    session_s = args.duration
    # The emulated module's server (pymodbus, in this process) logs an ERROR with a hex dump
    # whenever the recorder hangs up before an answer goes out, as it does at --duration.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL + 1)
    # switched on by the recorder's first request: however long the recorder takes to
    # start, its FIFO (12.8 s of scans, 1.3 s at x10) has not overflowed, and the file
    # holds no backlog stamped before the clock map knew the module's rate
    clock = HeldClock(speed)
    with Emulator(args.transport, source, clock=clock, seed=args.seed, truth_limit=10_000,
                  line=args.line) as emu:
        pace = "in real time" if speed == 1 else f"{speed:g} times as fast as wall time"
        print(f"\nThe emulated LDQ-412 runs {pace}: recording takes {session_s / speed:g} s.")
        status = _record(
            emu, clock, session_s,
            ["record", "--daq", emu.url, "--out", str(recordings),
             "--duration", f"{session_s / speed:g}", "--read-period", "0.05"],
        )  # fmt: skip
    if status != 0:
        return _end(t_start, status, f"failed (loopcal record exited with status {status})",
                    report)  # fmt: skip
    config = work / "controller.toml"
    status = _loopcal(["init-config", str(config), "--force"])
    if status != 0:
        return _end(t_start, status, f"failed (loopcal init-config exited with status {status})",
                    report)  # fmt: skip
    before = config.read_bytes()
    ties = ["--ties", args.ties] if args.ties else []
    status, out = _calibrate(
        ["calibrate", str(recordings), "--controller-config", str(config), "--free", args.free,
         *ties, "--method", args.method, "--write", "--report", str(work / "report")]
    )  # fmt: skip
    if config.read_bytes() == before:
        return _end(t_start, status, _nothing_written(status, out, config), report)
    report["written"] = True
    verdict = _against_truth(load_controller_config(config), truth, model, report["parameters"])
    return _end(t_start, status, verdict, report)


def _record(emu: Emulator, clock: HeldClock, session_s: float, argv: list[str]) -> int:
    """Run ``loopcal record``, saying every PROGRESS_S how much of the session it has
    recorded (device time since the driver's first request); its log is shown at the end."""
    print(f"\n{_command_line(argv)}", flush=True)
    with tempfile.TemporaryFile("w+") as log:
        proc = _start(argv, stdout=log, stderr=subprocess.STDOUT)
        talking_since: float | None = None
        due = time.monotonic() + PROGRESS_S
        while proc.poll() is None:
            try:
                proc.wait(timeout=0.2)
            except subprocess.TimeoutExpired:
                pass
            if talking_since is None and emu.first_request.is_set():
                talking_since = clock.now()
            if time.monotonic() < due or proc.returncode is not None:
                continue
            due += PROGRESS_S
            if talking_since is None:
                print("  recording: waiting for loopcal record to talk to the module", flush=True)
            else:
                done = min(clock.now() - talking_since, session_s)
                print(f"  recording: {_mmss(done)} of {_mmss(session_s)}", flush=True)
        log.seek(0)
        lines = log.read().strip().splitlines()
    print("\n".join(lines if proc.returncode != 0 else lines[-1:]), flush=True)
    return proc.returncode


def _mmss(seconds: float) -> str:
    return f"{int(seconds // 60)}:{int(seconds % 60):02d}"


# A failed gate as loopcal calibrate prints it (Gate.line): its name, then "why:" below.
_FAILED_GATE = re.compile(r"^\s*\[FAIL\] (\S+): .*\n\s*why: (.*)$", re.M)


def _calibrate(argv: list[str]) -> tuple[int, str]:
    """Run ``loopcal calibrate``, its output shown as it comes and kept for the verdict."""
    print(f"\n{_command_line(argv)}", flush=True)
    proc = _start(argv, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    kept: list[str] = []
    for line in proc.stdout:
        print(line, end="", flush=True)
        kept.append(line)
    return proc.wait(), "".join(kept)


def _nothing_written(status: int, calibrate_out: str, config: Path) -> str:
    """Say plainly that the config was left as it was, and why; return the verdict."""
    if status == 1:
        failed = _FAILED_GATE.findall(calibrate_out)
        reason = "; ".join(f"{name}: {why}" for name, why in failed) or "a gate failed"
        print(
            f"\nNothing was written: loopcal calibrate refused the session ({reason}); "
            f"{config} is as loopcal init-config wrote it."
        )
        if any(name == "poses" for name, _ in failed):
            print(f"In this demo a longer session (--duration, default {SESSION_S:g} s) passes "
                  "through more positions.")
        return f"refused ({reason}), nothing written"
    if status == 0:
        print(f"\nNothing was written: {config} already held the values calibrated.")
        return "accepted, nothing written (the config already held these values)"
    print(f"\nNothing was written: loopcal calibrate failed (exit status {status}, see above).")
    return f"failed (loopcal calibrate exited with status {status}), nothing written"


def _against_truth(written: ControllerConfig, truth: np.ndarray, model: ParameterModel,
                   table: dict[str, dict[str, float | None]]) -> str:  # fmt: skip
    """Print what was written next to the truth (and put it in ``table``: name -> written,
    truth, error, std); return the verdict."""
    from loopcal.calibration.parameters import INDEX, UNITS

    print("\nWhat was written, against the truth the simulation knows:")
    print(
        f"{'param':>6} {'unit':>5} {'written':>10} {'truth':>10} {'error':>8} {'std':>7} "
        f"{'err/std':>7}"
    )
    std = (written.provenance or {}).get("std", {})
    worst = 0.0
    no_std: list[str] = []
    for name in model.free:
        i = INDEX[name]
        err = written.params[i] - truth[i]
        s = std.get(name)
        table[name] = {"unit": UNITS[name], "written": float(written.params[i]),
                       "truth": float(truth[i]), "error": float(err), "std": s}  # fmt: skip
        if s:
            worst = max(worst, abs(err / s))
        else:
            no_std.append(name)
        print(
            f"{name:>6} {UNITS[name]:>5} {written.params[i]:10.4f} {truth[i]:10.4f} {err:+8.4f} "
            + (f"{s:7.4f} {err / s:+7.2f}" if s else f"{'-':>7} {'-':>7}")
        )
    if no_std:
        return f"written, but no std recorded for {', '.join(no_std)}"
    # rounded up, so that "within" holds for the printed number
    return f"written, every parameter within {math.ceil(worst * 10) / 10:.1f} std of the truth"


def _end(t_start: float, status: int, verdict: str, report: dict[str, Any]) -> int:
    seconds = time.perf_counter() - t_start
    print(f"\nDone in {seconds:.1f} s.")
    _say_files(Path(report["work"]), report["kept"])
    print(f"verdict: {verdict}", flush=True)
    report.update(verdict=verdict, seconds=round(seconds, 1))
    return status


def _say_files(work: Path, kept: bool) -> None:
    """Say where the demo's files are, or that they go with the temporary directory."""
    if not kept:
        print(f"Its files were in {work}, removed as the demo ends: --keep keeps them, "
              "--out DIR puts them where you choose.")  # fmt: skip
        return
    what = {
        "recordings": "the session's recording (loopcal info, check, export)",
        "controller.toml": "the controller config (calibrated if the verdict says written)",
        "report/index.html": "the calibration's HTML report",
    }
    print(f"Its files, in {work}:")
    for name, words in what.items():
        if (work / name).exists():
            print(f"  {work / name}: {words}")


def _command_line(argv: list[str]) -> str:
    """The command as a technician would type it: it pastes into a shell as it is."""
    return "$ " + shlex.join(["loopcal", *argv])


def _start(argv: list[str], **popen: Any) -> subprocess.Popen:
    """Start a ``loopcal`` command the way a technician's shell does: a process of its own,
    through the same entry point, its output to ours (stderr with --json)."""
    sys.stdout.flush()
    popen.setdefault("stdout", sys.stdout)
    return subprocess.Popen([sys.executable, "-m", "loopcal.daemon.cli", *argv], **popen)


def _loopcal(argv: list[str]) -> int:
    """Show and run a ``loopcal`` command, its output going straight to ours."""
    print(f"\n{_command_line(argv)}", flush=True)
    return _start(argv).wait()
