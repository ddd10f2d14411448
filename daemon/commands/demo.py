"""``loopcal demo``: the field job end to end, on the built-in emulated DAQ.

A simulated shoulder joint whose LVDT offsets were lost is moved by hand; its emulated
LDQ-412 is read through a real driver over a real transport; the still stretches become
poses; the best are selected; the parameters are identified and compared with the truth.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from calibration.parameters import NOMINAL
from calibration.pipeline import calibrate
from calibration.poses import still_poses
from calibration.simulate import perturbed_truth
from drivers import open_daq
from drivers.ldq412 import code_to_volts
from simulator import Emulator, ManualClock
from simulator.mechanism import MechanismSource
from simulator.scenarios import HandMoves

from .model_options import add_model_options, model_from_args

HELP = "calibrate a simulated shoulder joint whose LVDT offsets were lost, through its emulated DAQ"

FIFO_STEP_S = 1.0  # device seconds between FIFO reads (the FIFO holds 12.8 s at 20 Hz)


def run(args: argparse.Namespace) -> int:
    model = model_from_args(args)
    if args.minutes <= 0:
        raise ValueError("--minutes must be positive")
    if args.noise_mv < 0:
        raise ValueError("--noise-mv must not be negative")
    rng = np.random.default_rng(args.seed)
    truth = perturbed_truth(rng, offsets_mm=args.offset_error, model=model)
    print(
        f"Simulated shoulder joint: LVDTs refitted (offsets off by up to {args.offset_error} mm),"
        f" sensor noise {args.noise_mv:g} mV; identifying {model.describe()}"
    )
    t0 = time.perf_counter()
    source = MechanismSource(
        HandMoves(args.seed, params=truth), truth, noise_volts=args.noise_mv / 1000, seed=args.seed
    )
    clock = ManualClock()
    duration = 60.0 * args.minutes
    with Emulator(args.transport, source, clock=clock, seed=args.seed) as emu:
        with open_daq(emu.url, timeout=1.0) as daq:
            ident = daq.identity
            print(f"Emulated {ident.model} firmware {ident.firmware} at {emu.url}")
            # ASCII has no FIFO: poll once per scan; the Modbus drivers drain the FIFO
            step = FIFO_STEP_S if args.transport != "ascii" else 1.0 / 20
            scans = []
            for _ in range(round(duration / step)):
                clock.advance(step)
                scans += daq.read_scans()
    codes = np.array([s.codes for s in scans])
    valid = np.array([all(s.trustworthy) for s in scans])
    missed = sum(s.missed for s in scans)
    print(
        f"Read {len(scans)} scans ({args.minutes:g} min of a technician moving the plate by "
        f"hand): {missed} missed, {int((~valid).sum())} at the rail or faulted."
    )
    poses = still_poses(code_to_volts(codes), valid=valid)
    print(
        f"{len(poses)} still stretches averaged into poses "
        f"(median {int(np.median(poses.counts)) if len(poses) else 0} scans each)."
    )
    cal = calibrate(poses.volts, model, NOMINAL, n_select=args.select)
    sel, res = cal.selection, cal.identification
    print(
        f"Selected {len(sel.indices)} of {len(poses)} poses in {cal.rounds} round(s): "
        f"s_min {sel.indices_own.min_singular:.3g}, condition {sel.indices_own.condition:.3g}; "
        f"{100 * sel.bound_ratio:.1f} % of the certified best s_min."
    )
    print()
    print(res.table(truth))
    for problem in res.problems():
        print(f"WARNING: {problem}")
    print()
    offsets = ", ".join(f"d0{i + 1} = {v:.3f} mm" for i, v in enumerate(res.params[16:20]))
    print(f"New sensor offsets: {offsets}")
    print(f"Done in {time.perf_counter() - t0:.1f} s.")
    return 0 if not res.problems() else 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_model_options(p)
    p.add_argument(
        "--transport", choices=("modbus-tcp", "modbus-rtu", "ascii"), default="modbus-tcp"
    )
    p.add_argument("--minutes", type=float, default=5.0, help="recording length (5)")
    p.add_argument("--select", type=int, default=50, help="poses selected (default 50)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p.add_argument("--noise-mv", type=float, default=40.0, help="sensor noise, mV (40)")
    p.add_argument("--offset-error", type=float, default=3.0, help="how far offsets moved, mm")
