"""Playing recorded scans back through the emulated module, scan for scan.

The caller hands over arrays (the simulator knows nothing of recording formats): for each
power-on of the module, the scans' counters, device times and codes. The player serves them
on the emulated LDQ-412 so that a driver reading it gets the same counters, device times and
codes:

- the module starts as if powered on just before the first scan (``initial_uptime_s``, its
  FIFO drained), so its counter and time continue the recording's;
- between power-ons it is power-cycled (2 s off, as the datasheet says), so the counter and
  time start again at 0;
- each channel samples the recorded value of the scan at or before its instant (mid-code
  volts, which the converter turns back into the very same code); scans the recording
  missed repeat the one before.

Time is a :class:`~simulator.clock.ManualClock` the player advances, ``speed`` times as fast
as wall time, stepping exactly onto the power cycles, so nothing depends on thread timing.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from drivers.ldq412 import POWER_CYCLE_S, code_to_volts

from .clock import ManualClock
from .emulator import Emulator
from .mechanism import ReplaySource

STEP_S = 0.01  # wall time between clock advances
TAIL_S = 1.0  # device time served after the last scan, for the reader to catch up


@dataclass(frozen=True)
class RecordedPowerOn:
    """The scans of one power-on: counters (n,), device times since power-on (n,) in µs,
    codes (n, 4). Counters and times increase strictly."""

    counter: np.ndarray
    time_us: np.ndarray
    codes: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.counter)
        if n == 0 or self.time_us.shape != (n,) or self.codes.shape != (n, 4):
            raise ValueError("a power-on needs n >= 1 counters, n times and (n, 4) codes")
        if np.any(np.diff(self.counter) <= 0) or np.any(np.diff(self.time_us) <= 0):
            raise ValueError("counters and times of a power-on must increase")


class Player:
    """Serve recorded power-ons on an emulated module.

    transport: "modbus-tcp", "modbus-rtu" or "ascii". rate_hz: the recording's scan rate.
    speed: device seconds per wall second. The emulator starts with :meth:`start`; its
    :attr:`url` is what a driver opens; :meth:`run` plays until the end or ``stop``.
    """

    def __init__(
        self,
        power_ons: list[RecordedPowerOn],
        *,
        transport: str = "modbus-tcp",
        rate_hz: int = 20,
        speed: float = 1.0,
        host: str = "127.0.0.1",
        port: int = 0,
        seed: int = 0,
    ) -> None:
        if not power_ons:
            raise ValueError("nothing to replay")
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.power_ons = power_ons
        self.speed = float(speed)
        # Device (source) time of every scan: the first power-on runs from its own start;
        # each later one boots POWER_CYCLE_S after a cycle one period past the previous end.
        period = 1.0 / rate_hz
        times, boots, t_end = [], [], 0.0
        for k, po in enumerate(power_ons):
            boot = 0.0 if k == 0 else t_end + period + POWER_CYCLE_S
            if k:
                boots.append(t_end + period)
            t = boot + po.time_us / 1e6
            times.append(t)
            t_end = float(t[-1])
        self.cycles = boots  # device times at which the module is switched off
        self.end_s = t_end + TAIL_S
        all_times = np.concatenate(times)
        volts = code_to_volts(np.concatenate([po.codes for po in power_ons]))
        self.source = ReplaySource(all_times, volts, start_s=float(all_times[0]))
        self.clock = ManualClock()
        first_us = int(power_ons[0].time_us[0])
        # powered on just before the first scan (or at it, when that is the power-on's first)
        start_s = max(first_us - 1, 0) / 1e6
        self.clock.advance(start_s)
        self.emulator = Emulator(
            transport, self.source, scan_rate_hz=rate_hz, clock=self.clock, seed=seed,
            initial_uptime_s=start_s, drained=first_us > 0, host=host, port=port,
        )  # fmt: skip
        self._t0 = start_s

    @property
    def url(self) -> str:
        return self.emulator.url

    def start(self) -> Player:
        self.emulator.start()
        return self

    def close(self) -> None:
        self.emulator.close()

    def __enter__(self) -> Player:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run(self, stop: threading.Event | None = None, *, wait_for_client: bool = False) -> bool:
        """Advance the clock until the end (True) or ``stop`` (False).

        wait_for_client: hold the first scan until a driver's first request, so that a
        client that starts slowly (or a FIFO a few seconds deep at a high ``speed``) misses
        nothing of the recording.
        """
        stop = stop or threading.Event()
        if wait_for_client:
            while not self.emulator.first_request.wait(STEP_S):
                if stop.is_set():
                    return False
        cycles = list(self.cycles)
        wall0 = time.monotonic()
        while not stop.is_set():
            target = min(self._t0 + (time.monotonic() - wall0) * self.speed, self.end_s)
            now = self.clock.now()
            while cycles and cycles[0] <= target:
                self.clock.advance(max(0.0, cycles.pop(0) - now))
                self.emulator.faults.restart(POWER_CYCLE_S)
                now = self.clock.now()
            if target > now:
                self.clock.advance(target - now)
            if target >= self.end_s:
                return True
            stop.wait(STEP_S)
        return False
