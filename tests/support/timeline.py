"""A module's scan timeline against the host's clock, in simulated time: for testing and
benchmarking the poll schedule (drivers/pacing.py) and the time stamps
(daemon/recorder/clockmap.py) over hours in seconds. Pure arithmetic, the module as the
datasheet and the emulator's open points describe it: scan k of a power-on at device time
``phase + k * period`` (its own µs), readable from host time
``(phase + k * period) / (1 + ppm)``; a request decided when it arrives, its answer sent
after a latency."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from loopcal.drivers import Scan
from loopcal.drivers.pacing import FIFO_READ_PERIOD_S, FifoPacer, PollPacer
from loopcal.simulator.open_points import Latency

from .rows import T0


@dataclass
class Module:
    """rate_hz, ppm (its clock against the host's), phase_us (scan 0 after power-on),
    boot_s (host time of the power-on)."""

    rate_hz: int = 20
    ppm: float = 0.0
    phase_us: int = 0
    boot_s: float = 0.0

    @property
    def period_us(self) -> int:
        return 1_000_000 // self.rate_hz

    def latest(self, host_s: float) -> int:
        """Counter of the latest scan at host time ``host_s`` (-1: none yet)."""
        dev_us = (host_s - self.boot_s) * 1e6 * (1 + self.ppm * 1e-6)
        return int(np.floor((dev_us - self.phase_us) / self.period_us))

    def time_us(self, k: int) -> int:
        return self.phase_us + k * self.period_us

    def readable_s(self, k: int) -> float:
        return self.boot_s + self.time_us(k) * 1e-6 / (1 + self.ppm * 1e-6)


@dataclass
class PollRun:
    polls: int = 0
    scans: int = 0  # scans the module made from the first delivered one to the last
    delivered: int = 0
    missed: int = 0
    missed_after_slow: int = 0  # missed right after an answer slower than a period
    offsets_ms: list[float] = field(default_factory=list)  # poll send - scan edge, ms


def run_polls(
    module: Module,
    seconds: float,
    latency_s: Callable[[], float],
    *,
    lock: PollPacer | None = None,
    transit_s: float = 0.0002,
) -> PollRun:
    """Poll ``module`` for ``seconds`` of host time with a PollPacer (or anything with its
    two methods), sequentially (the next poll after the previous answer), and count what
    was read."""
    lock = lock or PollPacer(module.rate_hz)
    out = PollRun()
    now, last_k, first_k, slow = module.boot_s + 0.01, None, None, False
    t_end = module.boot_s + seconds
    while now < t_end:
        sent = lock.next_read(now)
        arrival = sent + transit_s
        k = module.latest(arrival)
        lat = latency_s()
        received = arrival + lat
        out.polls += 1
        new = k >= 0 and (last_k is None or k > last_k)
        scans = []
        if new:
            if last_k is not None:
                gap = k - last_k - 1
                out.missed += gap
                if slow:
                    out.missed_after_slow += gap
            else:
                first_k = k
            last_k = k
            out.delivered += 1
            time_us = module.time_us(k)
            scans = [Scan(k, time_us, (0, 0, 0, 0), 0, k, time_us, host_time=received)]
            out.offsets_ms.append((sent - module.readable_s(k)) * 1e3)
        lock.observe(sent, received, scans)
        slow = lat + transit_s > 1.0 / module.rate_hz / 2
        now = received
    if first_k is not None and last_k is not None:
        out.scans = last_k - first_k + 1
    return out


def datasheet_latency(rng: np.random.Generator, slow: float = 0.0) -> Callable[[], float]:
    """The emulator's latency model over Modbus TCP
    (:class:`loopcal.simulator.open_points.Latency`): uniform(0.5, 10) ms, with ``slow`` of them
    50-90 ms; s."""
    return partial(Latency(slow_fraction=slow).draw_s, rng, "modbus-tcp")


@dataclass
class StampRun:
    """Stamps against the truth over a simulated run (ms)."""

    errors_ms: np.ndarray  # stamp - the scan's true UTC instant, every scan
    receive_ms: np.ndarray  # host receive - stamp, for the scans read as the latest
    backwards: int  # stamps that did not increase


def run_stamps(
    clockmap,
    module: Module,
    hours: float,
    latency_s: Callable[[], float],
    *,
    read_period_s: float = FIFO_READ_PERIOD_S,
    utc0_ns: int = T0,
    jitter_s: float = 0.002,
    dither: bool = True,
    sync_first: bool = True,
    rng: np.random.Generator | None = None,
) -> StampRun:
    """FIFO reads every ``read_period_s`` (± ``jitter_s``, plus the acquisition's dither
    of up to one scan period): a snapshot (the anchor, the latest scan, answered after a
    latency) and the scans since the last read, stamped as the acquisition does (one
    observation per read, of the anchor); ``clockmap`` is a fresh
    :class:`loopcal.daemon.recorder.clockmap.ClockMap` or anything with its two methods."""
    rng = rng or np.random.default_rng(0)
    n_reads = int(hours * 3600 / read_period_s)
    errors, receive, backwards = [], [], 0
    last_k, last_stamp = -1, None
    t = module.boot_s + 0.5
    if sync_first:  # the acquisition catches a new scan at the start of an epoch
        k0 = module.latest(t)
        edge = module.readable_s(k0 + 1) + latency_s()
        clockmap.observe(edge, utc0_ns + round(edge * 1e9), module.time_us(k0 + 1))
    pacer = FifoPacer(read_period_s, module.rate_hz)  # the acquisition's, for its dither
    for _ in range(n_reads):
        extra = pacer.dither() if dither else 0.0
        pacer.observe(t, t, ())  # counts the read (never half full here)
        t += read_period_s + extra + rng.uniform(-jitter_s, jitter_s)
        k = module.latest(t)
        arrival = t + latency_s()
        if k <= last_k:
            continue
        ks = np.arange(last_k + 1, k + 1)
        last_k = k
        arrival_ns = utc0_ns + round(arrival * 1e9)
        clockmap.observe(arrival, arrival_ns, module.time_us(k))
        stamps = clockmap.stamps(module.phase_us + ks * module.period_us)
        true_s = [module.readable_s(int(j)) for j in ks]
        true = utc0_ns + np.round(np.array(true_s) * 1e9)
        errors.append((stamps - true) / 1e6)
        receive.append((arrival_ns - stamps[-1]) / 1e6)
        if last_stamp is not None:
            backwards += int(stamps[0] <= last_stamp) + int(np.sum(np.diff(stamps) <= 0))
        last_stamp = int(stamps[-1])
    return StampRun(np.concatenate(errors), np.array(receive), backwards)
