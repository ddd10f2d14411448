"""``loopcal demo``: the field job for real, on the built-in emulated DAQ.

A simulated shoulder joint whose LVDTs were refitted (offsets lost, known only to the
simulation) is moved by a technician's hand, pausing about a second at each position. Its
emulated LDQ-412 is recorded by ``loopcal record`` through a real driver over a real
transport; ``loopcal calibrate --write`` turns the recording into new values in a fresh
controller config (``loopcal init-config``); and what was written is compared with the truth.
The emulated module runs ``--speed`` times as fast as wall time, so two minutes of session
take about twelve seconds.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from loopcal.calibration.identify import DEFAULT_METHOD, METHODS
from loopcal.calibration.parameters import INDEX, UNITS, ParameterModel
from loopcal.calibration.simulate import perturbed_truth
from loopcal.simulator import Emulator
from loopcal.simulator.clock import HeldClock
from loopcal.simulator.emulator import TRANSPORTS
from loopcal.simulator.mechanism import MechanismSource
from loopcal.simulator.scenarios import HandMoves

from ..config.controller import load_controller_config

PAUSE_S = (0.8, 1.5)  # a technician pausing about a second at each position


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--transport", choices=TRANSPORTS, default="modbus-tcp")
    p.add_argument("--minutes", type=float, default=2.0, help="session length (2)")
    p.add_argument(
        "--speed",
        type=float,
        default=None,
        help="device time per real second (default 10; 1 over ASCII, which polls)",
    )
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p.add_argument("--noise-mv", type=float, default=40.0, help="sensor noise, mV (40)")
    p.add_argument(
        "--offset-error",
        type=float,
        default=3.0,
        help="how far the refitted sensors' offsets moved, mm (3)",
    )
    p.add_argument("--free", default="paper7", help="what to identify (default paper7)")
    p.add_argument(
        "--method",
        choices=METHODS,
        default=DEFAULT_METHOD,
        help=f"estimator for loopcal calibrate (default {DEFAULT_METHOD})",
    )
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="keep the recording, config and report here (default: a temp dir)",
    )


def run(args: argparse.Namespace) -> int:
    if args.minutes <= 0:
        raise ValueError("--minutes must be positive")
    if args.noise_mv < 0:
        raise ValueError("--noise-mv must not be negative")
    speed = args.speed if args.speed is not None else (1.0 if args.transport == "ascii" else 10.0)
    if speed <= 0:
        raise ValueError("--speed must be positive")
    model = ParameterModel.parse(args.free)
    if args.out is None:
        work = Path(tempfile.mkdtemp(prefix="loopcal-demo-"))
    else:
        work = args.out
        if work.exists() and not work.is_dir():
            raise ValueError(f"--out {work}: exists and is not a directory")
        try:
            work.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ValueError(f"--out {work}: cannot create it: {exc.strerror or exc}") from None
    t_start = time.perf_counter()
    truth = perturbed_truth(
        np.random.default_rng(args.seed), offsets_mm=args.offset_error, model=model
    )
    print(
        f"A shoulder joint whose LVDTs were refitted (offsets off by up to "
        f"{args.offset_error:g} mm), {args.noise_mv:g} mV of sensor noise; a technician moves "
        f"it by hand for {args.minutes:g} min. Working in {work}."
    )
    source = MechanismSource(
        HandMoves(args.seed, params=truth, pause_s=PAUSE_S),
        truth,
        noise_volts=args.noise_mv / 1000,
        seed=args.seed,
    )
    recordings = work / "recordings"
    # switched on by the recorder's first request: however long the recorder takes to
    # start, its FIFO (12.8 s of scans, 1.3 s at x10) has not overflowed, and the file
    # holds no backlog stamped before the clock map knew the module's rate
    with Emulator(
        args.transport, source, clock=HeldClock(speed), seed=args.seed, truth_limit=10_000
    ) as emu:
        print(f"\n$ loopcal record --daq {emu.url} --out {recordings}   (x{speed:g})", flush=True)
        rec = _loopcal(
            "record", "--daq", emu.url, "--out", str(recordings),
            "--duration", f"{args.minutes * 60 / speed:g}", "--read-period", "0.05",
            capture=True,
        )  # fmt: skip
    lines = rec.stderr.strip().splitlines()
    print("\n".join(lines[-1:]))
    if rec.returncode != 0:
        print(rec.stderr, file=sys.stderr)
        return rec.returncode
    config = work / "controller.toml"
    print(f"\n$ loopcal init-config {config} --force")
    made = _loopcal("init-config", str(config), "--force")
    if made.returncode != 0:
        return made.returncode
    print(
        f"\n$ loopcal calibrate {recordings} --controller-config {config} --free {args.free} "
        f"--method {args.method} --write --report {work / 'report'}",
        flush=True,
    )
    status = _loopcal(
        "calibrate", str(recordings), "--controller-config", str(config), "--free", args.free,
        "--method", args.method, "--write", "--report", str(work / "report"),
    ).returncode  # fmt: skip
    if not config.exists():
        return status
    written = load_controller_config(config)
    print("\nWhat was written, against the truth the simulation knows:")
    print(
        f"{'param':>6} {'unit':>5} {'written':>10} {'truth':>10} {'error':>8} {'std':>7} "
        f"{'err/std':>7}"
    )
    std = (written.provenance or {}).get("std", {})
    for name in model.free:
        i = INDEX[name]
        err = written.params[i] - truth[i]
        s = std.get(name)
        z = f"{err / s:+7.2f}" if s else "      -"
        print(
            f"{name:>6} {UNITS[name]:>5} {written.params[i]:10.4f} {truth[i]:10.4f} {err:+8.4f} "
            f"{s if s else float('nan'):7.4f} {z}"
        )
    print(f"\nDone in {time.perf_counter() - t_start:.1f} s.")
    return status


def _loopcal(*argv: str, capture: bool = False) -> subprocess.CompletedProcess:
    """Run a ``loopcal`` command the way a technician's shell does: a process of its own,
    through the same entry point (its output goes straight to ours unless ``capture``)."""
    return subprocess.run(
        [sys.executable, "-m", "loopcal.daemon.cli", *argv], capture_output=capture, text=True
    )
