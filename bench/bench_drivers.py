"""Sustained scans per second each LDQ-412 driver reads from the emulator.

Three figures per transport, each the median over --repeats runs:

* ``fifo capacity``: the emulator's clock is a ManualClock; each step produces a full FIFO
  (256 scans) at once and times one read_scans() that drains it (1 snapshot + 13 FIFO
  reads). scans / wall second = the highest scan production the driver can keep up with.
* ``fifo real time``: a free-running SimClock makes the module produce ``--target`` scans
  per wall second (200 Hz scan rate, clock sped up); read_scans() runs in a loop for
  --seconds. Reports scans delivered per second and scans missed (0 = sustained).
* ``snapshot polling``: ManualClock advanced by one scan period before each poll, so
  every poll yields one new scan: polls (= scans) per wall second, the ceiling of the
  polling mode (ASCII, or Modbus with fifo=0).

Run: ``python -m bench.bench_drivers [--repeats 5] [--seconds 2] [--target 1000]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

from loopcal.drivers import DAQ, ldq412, open_daq
from loopcal.simulator.clock import ManualClock, SimClock
from loopcal.simulator.emulator import Emulator

RATE = 200


def fifo_capacity(transport: str, rounds: int = 10) -> float:
    clock = ManualClock()
    with Emulator(transport, clock=clock, scan_rate_hz=RATE) as emu, open_daq(emu.url) as daq:
        daq.read_scans()
        n, elapsed = 0, 0.0
        for _ in range(rounds):
            clock.advance(ldq412.FIFO_DEPTH / RATE)
            t0 = time.perf_counter()
            scans = daq.read_scans()
            elapsed += time.perf_counter() - t0
            n += len(scans)
            assert all(s.missed == 0 for s in scans[1:])
        return n / elapsed


def fifo_real_time(transport: str, target: float, seconds: float) -> tuple[float, int]:
    clock = SimClock(target / RATE)
    with Emulator(transport, clock=clock, scan_rate_hz=RATE) as emu, open_daq(emu.url) as daq:
        daq.read_scans()
        n = missed = 0
        t0 = time.perf_counter()
        while (elapsed := time.perf_counter() - t0) < seconds:
            scans = daq.read_scans()
            n += len(scans)
            missed += sum(s.missed for s in scans)
            time.sleep(0.005)
        return n / elapsed, missed


def polling(transport: str, polls: int = 1000) -> float:
    clock = ManualClock()
    suffix = "&fifo=0" if transport.startswith("modbus") else ""
    with Emulator(transport, clock=clock, scan_rate_hz=RATE) as emu:
        daq: DAQ
        with open_daq(emu.url + suffix) as daq:
            daq.read_scans()
            n = 0
            t0 = time.perf_counter()
            for _ in range(polls):
                clock.advance(1 / RATE)
                n += len(daq.read_scans())
            elapsed = time.perf_counter() - t0
            assert n == polls
            return n / elapsed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument(
        "--target",
        type=float,
        default=1000.0,
        help="scans per wall second produced in the real-time FIFO run",
    )
    ap.add_argument("--json", action="store_true", help="print the results as JSON")
    args = ap.parse_args(argv)

    results: dict[str, dict[str, float]] = {}
    for transport in ("modbus-tcp", "modbus-rtu", "ascii"):
        row: dict[str, float] = {}
        if transport != "ascii":
            row["fifo_capacity_scans_per_s"] = statistics.median(
                fifo_capacity(transport) for _ in range(args.repeats)
            )
            rt = [fifo_real_time(transport, args.target, args.seconds) for _ in range(args.repeats)]
            row["fifo_real_time_scans_per_s"] = statistics.median(r[0] for r in rt)
            row["fifo_real_time_missed_total"] = sum(r[1] for r in rt)
        row["polling_scans_per_s"] = statistics.median(
            polling(transport) for _ in range(args.repeats)
        )
        results[transport] = row

    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(
            f"LDQ-412 drivers vs emulator, median of {args.repeats} runs "
            f"(real-time FIFO target {args.target:.0f} scans/s)"
        )
        print(
            f"{'transport':<12}{'FIFO capacity':>16}{'FIFO real time':>18}"
            f"{'missed':>8}{'polling':>12}   [scans/s]"
        )
        for transport, row in results.items():
            cap = row.get("fifo_capacity_scans_per_s")
            rt = row.get("fifo_real_time_scans_per_s")
            missed = row.get("fifo_real_time_missed_total")
            print(
                f"{transport:<12}"
                f"{'-' if cap is None else f'{cap:.0f}':>16}"
                f"{'-' if rt is None else f'{rt:.0f}':>18}"
                f"{'-' if missed is None else f'{missed:.0f}':>8}"
                f"{row['polling_scans_per_s']:>12.0f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
