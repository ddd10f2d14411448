"""``loopcal replay REC.mcap ... [--transport modbus-tcp|modbus-rtu|ascii] [--speed X]``:
serve a recording through the emulated DAQ, scan for scan.

Prints the URL to open (for serial transports also the pseudo-terminal), like
``loopcal simulate``, then plays the recording's scans with their counters, device times and
codes: recording the replay gives them back. Each power-on of the module in the recording is
one power-on of the emulated module. Exits 0 once everything was played (or on SIGINT /
SIGTERM), 2 for bad input.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from typing import TYPE_CHECKING

from loopcal.drivers.ldq412 import POWER_CYCLE_S
from loopcal.simulator.arguments import (
    add_speed_option,
    add_transport_option,
    listen_host,
    tcp_port,
)
from loopcal.simulator.open_points import add_arguments as add_open_point_arguments

from ..arguments import add_recordings_argument
from .errors import CommandError

if TYPE_CHECKING:  # the player and the recordings (numpy, pymodbus): imported to run
    import numpy as np

    from loopcal.simulator.replay import RecordedPowerOn

OFF_MIN_S = 0.1  # shortest power cycle replayed


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_recordings_argument(p)
    add_transport_option(p, "the wire the replayed module answers on")
    add_speed_option(p)
    p.add_argument(
        "--start-now",
        action="store_true",
        help="play at once (default: hold the first scan until a client's first request)",
    )
    p.add_argument(
        "--host", type=listen_host, default="127.0.0.1", help="TCP address (default 127.0.0.1)"
    )
    p.add_argument("--port", type=tcp_port, default=0, help="TCP port (default: a free one)")
    add_open_point_arguments(p, scanning=False)


def power_ons(scans: np.ndarray) -> list[RecordedPowerOn]:
    """The recording's scans split by power-on epoch, as arrays for the player: the
    recorded counters, device times, codes and status themselves (the restart flag at the
    first scan as the recording saw it; the time off before each restart from the stamps,
    within the datasheet's 2 s)."""
    import numpy as np

    from loopcal.simulator.replay import RecordedPowerOn

    out: list[RecordedPowerOn] = []
    epochs = scans["epoch"]
    cuts = np.flatnonzero(np.diff(epochs)) + 1
    prev_ns = None
    for k, part in enumerate(np.split(scans, cuts)):
        first_ns = int(part["stamp_ns"][0]) - int(part["time64_us"][0]) * 1000  # its power-on
        off_s = POWER_CYCLE_S if prev_ns is None else (first_ns - prev_ns) / 1e9
        out.append(
            RecordedPowerOn(
                part["counter64"].astype(np.int64),
                part["time64_us"].astype(np.int64),
                part["codes"].astype(np.int64),
                part["status"].astype(np.int64),
                restart_latched=bool(part["restarted"][0]) or k > 0,
                off_s=min(POWER_CYCLE_S, max(OFF_MIN_S, off_s)),
            )
        )
        prev_ns = int(part["stamp_ns"][-1])
    return out


def run(args: argparse.Namespace) -> int:
    from loopcal.simulator.open_points import from_arguments as open_points_from_arguments
    from loopcal.simulator.replay import Player

    from ..recording import read_recordings
    from ..scan_rows import scan_rate_hz

    try:
        open_points = open_points_from_arguments(args)
    except ValueError as exc:  # the open points' options, named
        raise CommandError(exc) from None
    try:
        rec = read_recordings(args.recordings)
    except OSError as exc:
        raise CommandError(exc) from None
    if len(rec) == 0:
        names = ", ".join(str(p) for p in args.recordings)
        raise CommandError(f"{names}: no scans in the recording(s)")
    for line in rec.warnings:
        print(f"warning: {line}", file=sys.stderr, flush=True)
    meta_rate = rec.files[0].metadata.get("device", {}).get("scan_rate_hz")
    rate = int(meta_rate) if meta_rate else round(scan_rate_hz(rec.scans))
    player = Player(
        power_ons(rec.scans),
        transport=args.transport,
        rate_hz=rate,
        speed=args.speed,
        host=args.host,
        port=args.port,
        open_points=open_points,
        line=args.line,
    )
    try:
        player.start()
    except (RuntimeError, OSError) as exc:  # the servers cannot start: the port is in use
        raise CommandError(exc) from None
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    with player:
        print(f"listening: {player.url}", flush=True)
        if player.emulator.link is not None:
            print(f"serial device: {player.url.split('://', 1)[1].split('?')[0]}", flush=True)
        print(
            f"replaying {len(rec):,} scans in {len(player.power_ons)} power-on(s) at {rate} Hz, "
            f"x{args.speed:g}" + ("" if args.start_now else ", from a client's first request"),
            flush=True,
        )
        done = player.run(stop, wait_for_client=not args.start_now)
    print("replay finished" if done else "replay stopped", flush=True)
    return 0
