"""Time stamps and poll schedule against a module whose clock is not the host's, over
simulated hours (pure arithmetic: tests/support/timeline.py; the datasheet's answer times,
0.5-10 ms).

Stamps (FIFO reads every read period, 0.5 s): the recorder's stamp of every scan against
the host time the scan was really taken, and, for the scans an answer carried as the
latest, against the host receive time; baseline: the former map (the smallest arrival -
device time of the last minute, reads every read period without the dither), in the same
run. And what the floor that keeps stamps in order costs: how many stamps it raised above
the map's line, by how much.

Polls (no FIFO, 20 Hz): polls per scan and scans missed by the phase lock; baseline: the
former schedule (just after the next scan is due by the smallest arrival delay seen).

Run: ``python -m bench.bench_stamps [--hours 6] [--ppm 200 -200 0 1000 -1000] [--rate 20]``
(``--rate``: the module's scan rate for the stamps, Hz).
"""

from __future__ import annotations

import argparse
import collections
import time

import numpy as np

from loopcal.daemon.recorder.clockmap import ClockMap
from loopcal.drivers.pacing import FIFO_READ_PERIOD_S
from tests.support.timeline import Module, datasheet_latency, run_polls, run_stamps


class FormerClockMap:
    """The map before issue 13: the smallest (arrival - device time) of the last minute."""

    def __init__(self) -> None:
        self._samples: collections.deque[tuple[float, int]] = collections.deque()
        self.offset_ns: int | None = None
        self._last_stamp = -(1 << 62)

    def observe(self, mono_s: float, arrival_ns: int, time64_us: int) -> None:
        sample = arrival_ns - time64_us * 1000
        q = self._samples
        while q and q[-1][1] >= sample:
            q.pop()
        q.append((mono_s, sample))
        while q[0][0] < mono_s - 60.0:
            q.popleft()
        self.offset_ns = q[0][1]

    def stamps(self, time64_us: np.ndarray) -> np.ndarray:
        assert self.offset_ns is not None
        s = time64_us.astype(np.int64) * 1000 + self.offset_ns
        s = np.maximum(s, self._last_stamp + 1 + np.arange(len(s)))
        self._last_stamp = int(s[-1])
        return s


class FlooredMap:
    """The recorder's map, noting what its floor did: how many stamps it raised above the
    line, and by how much (the accuracy the rule that keeps stamps in order costs)."""

    def __init__(self) -> None:
        self.map = ClockMap()
        self.stamped = 0
        self.raised_ns: list[int] = []

    def observe(self, mono_s: float, arrival_ns: int, time64_us: int) -> None:
        self.map.observe(mono_s, arrival_ns, time64_us)

    def stamps(self, time64_us: np.ndarray) -> np.ndarray:
        line = self.map.line_stamps(time64_us)
        s = self.map.stamps(time64_us)
        self.stamped += len(s)
        self.raised_ns += (s - line)[s > line].tolist()
        return s


class FormerPollSchedule:
    """The poll schedule before issue 13: just after the next scan is due, by device time
    plus the smallest arrival delay seen (which its own polls kept where they were)."""

    def __init__(self, rate_hz: int) -> None:
        self.period = 1.0 / rate_hz
        self.clock = FormerClockMap()
        self._newest_us: int | None = None
        self._new = False
        self._sent = 0.0

    def observe(self, sent: float, received: float, scans: list) -> None:
        self._sent, self._new = sent, bool(scans)
        if scans:
            self._newest_us = scans[-1].time64_us
            self.clock.observe(received, round(received * 1e9), self._newest_us)

    def next_read(self, now: float) -> float:
        if not self._new or self._newest_us is None or self.clock.offset_ns is None:
            return now + min(0.005, self.period / 4)
        due = (self._newest_us * 1000 + self.clock.offset_ns) * 1e-9 + self.period + 0.003
        return min(max(due, self._sent + 0.002), self._sent + self.period)


def stamp_figures(hours: float, ppm: float, rate_hz: int = 20) -> None:
    rows = []
    floored = FlooredMap()
    for name, cm, dither in (("former", FormerClockMap(), False), ("now", floored, True)):
        t0 = time.perf_counter()
        run = run_stamps(
            cm,
            Module(rate_hz=rate_hz, ppm=ppm, phase_us=1809),
            hours,
            datasheet_latency(np.random.default_rng(7)),
            dither=dither,
            rng=np.random.default_rng(8),
        )
        settled = np.abs(run.errors_ms[rate_hz * 60 :])  # after the first minute
        rows.append((name, run, settled, time.perf_counter() - t0))
    (_, _, old, _), (_, run, new, took) = rows
    print(
        f"stamps, {hours:g} h at {ppm:+g} ppm, {rate_hz} Hz: max |stamp - true| {new.max():.2f} ms "
        f"(p99 {np.percentile(new, 99):.2f}, median {np.median(new):.2f}) after the first "
        f"minute, {np.abs(run.errors_ms).max():.1f} ms in it; former {old.max():.2f} ms "
        f"(p99 {np.percentile(old, 99):.2f}): ratio {old.max() / new.max():.1f}x"
    )
    rcv = run.receive_ms[int(60 / FIFO_READ_PERIOD_S) :]  # after the first minute
    print(
        f"    receive - stamp for the latest scan of each read: min {rcv.min():.2f} ms "
        f"({run.receive_ms.min():.2f} in the first minute), median {np.median(rcv):.2f}, "
        f"max {rcv.max():.2f}; stamps not increasing: {run.backwards}; {took:.1f} s to simulate"
    )
    raised = np.array(floored.raised_ns, dtype=np.float64) / 1e6
    print(
        f"    the floor (each stamp at least 1 ns after the last) raised {len(raised)} of "
        f"{floored.stamped:,} stamps above the line"
        + (
            f", by at most {raised.max():.3f} ms (median {np.median(raised):.3f})"
            if len(raised)
            else ""
        )
    )


def poll_figures(hours: float, ppm: float) -> None:
    out = {}
    for name, make in (("former", FormerPollSchedule), ("now", None)):
        lock = make(20) if make else None
        run = run_polls(
            Module(ppm=ppm, phase_us=1809, boot_s=1.0),
            hours * 3600,
            datasheet_latency(np.random.default_rng(9)),
            lock=lock,
        )
        out[name] = run
    old, new = out["former"], out["now"]
    print(
        f"polls, {hours:g} h at {ppm:+g} ppm: {new.polls / new.scans:.4f} polls per scan, "
        f"{new.missed} scans missed of {new.scans:,}; former {old.polls / old.scans:.4f} "
        f"polls per scan, {old.missed} missed"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=6.0)
    ap.add_argument("--ppm", type=float, nargs="+", default=[200.0, -200.0, 0.0, 1000.0, -1000.0])
    ap.add_argument("--rate", type=int, default=20, help="scan rate for the stamps, Hz (20)")
    args = ap.parse_args()
    for ppm in args.ppm:
        stamp_figures(args.hours, ppm, args.rate)
    for ppm in args.ppm:
        poll_figures(args.hours, ppm)


if __name__ == "__main__":
    main()
