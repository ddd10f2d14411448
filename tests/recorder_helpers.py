"""Helpers for the recorder tests: an emulated DAQ in this process, the recorder as a real
subprocess (``loopcal record`` / ``loopcal daemon``), its log lines as they come."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from prometheus_client.parser import text_string_to_metric_families

from loopcal.calibration.parameters import NOMINAL
from loopcal.simulator import Emulator
from loopcal.simulator.clock import Clock, HeldClock
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.mechanism import MechanismSource
from loopcal.simulator.open_points import OpenPoints
from loopcal.simulator.scenarios import HandMoves

LOOPCAL = [sys.executable, "-m", "loopcal.daemon.cli"]


def hand_emulator(
    transport: str = "modbus-tcp",
    *,
    rate: int = 20,
    speed: float = 1.0,
    seed: int = 0,
    drifts: tuple[OffsetDrift, ...] = (),
    clock: Clock | None = None,
    open_points: OpenPoints | None = None,
) -> Emulator:
    """An emulated LDQ-412 on a technician-moved shoulder joint (not started), whose clock
    (``speed`` times wall time) starts at the recorder's first request: however long the
    recorder subprocess takes to start on a busy machine, the FIFO (1.28 s deep at 200 Hz)
    does not overflow before it connects. ``clock``: another clock instead (``speed`` is
    then not used); ``open_points``: the emulator's settings for what the datasheet leaves
    open."""
    if clock is None:
        clock = HeldClock(speed)  # the emulator starts it at the first request
    source = MechanismSource(HandMoves(seed), NOMINAL, noise_volts=0.04, seed=seed, drifts=drifts)
    return Emulator(transport, source, scan_rate_hz=rate, clock=clock, seed=seed,
                    open_points=open_points)  # fmt: skip


class Proc:
    """A loopcal subprocess whose stderr lines are collected as they arrive."""

    def __init__(
        self,
        args: list[str],
        *,
        env: dict[str, str] | None = None,
        preexec_fn: Callable[[], None] | None = None,
    ) -> None:
        self.args = args
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self.proc = subprocess.Popen(
            [*LOOPCAL, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env={**os.environ, **(env or {})},
            preexec_fn=preexec_fn,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    @property
    def pid(self) -> int:
        return self.proc.pid

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    def wait_for(self, pattern: str, timeout: float = 10.0, *, after: int = 0) -> int:
        """Index of the first log line from ``after`` on matching ``pattern``."""
        rx = re.compile(pattern)
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for i in range(after, len(self.lines)):
                    if rx.search(self.lines[i]):
                        return i
                left = deadline - time.monotonic()
                if left <= 0 or self.proc.poll() is not None and not self._reader.is_alive():
                    raise AssertionError(
                        f"no log line matching {pattern!r} within {timeout} s:\n" + self.text
                    )
                self._cond.wait(min(left, 0.1))

    @property
    def text(self) -> str:
        with self._cond:
            return "\n".join(self.lines)

    def signal(self, sig: signal.Signals) -> None:
        self.proc.send_signal(sig)

    def stop(self, timeout: float = 10.0) -> tuple[int, float]:
        """SIGTERM; returns (exit status, seconds it took to exit)."""
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        rc = self.proc.wait(timeout)
        took = time.monotonic() - t0
        self._reader.join(5)
        return rc, took

    def wait(self, timeout: float = 30.0) -> int:
        rc = self.proc.wait(timeout)
        self._reader.join(5)
        return rc

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._reader.join(5)


def listening_url(proc: Proc, timeout: float = 10.0) -> str:
    """The URL a ``loopcal simulate`` or ``loopcal replay`` subprocess says it listens on."""
    return proc.lines[proc.wait_for("listening: ", timeout)].split(": ", 1)[1]


def record(url: str, out: Path, *extra: str, **kw) -> Proc:
    """``loopcal record --daq URL --out DIR ...`` as a subprocess."""
    return Proc(["record", "--daq", url, "--out", str(out), *extra], **kw)


def scrape(port: int) -> dict[str, list]:
    """name -> [(labels, value)] of every sample a recorder's /metrics serves."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        text = r.read().decode()
    out: dict[str, list] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out.setdefault(s.name, []).append((s.labels, s.value))
    return out


def value(m: dict, name: str, **labels: str) -> float:
    [v] = [v for lab, v in m[name] if all(lab.get(k) == x for k, x in labels.items())]
    return v


def truth_table(emu: Emulator) -> dict[tuple[int, int], tuple[int, tuple[int, ...]]]:
    """(boot, counter) -> (time_us, codes) of every scan the emulated module made."""
    return {(s.boot, s.counter): (s.time_us, s.codes) for s in emu.truth}


def assert_matches_truth(rows: np.ndarray, emu: Emulator, *, boot_of_epoch=lambda e: e) -> None:
    """Every recorded scan is the module's scan with that counter, bit for bit."""
    truth = truth_table(emu)
    for r in rows:
        key = (boot_of_epoch(int(r["epoch"])), int(r["counter64"]) & 0xFFFFFFFF)
        assert key in truth, f"recorded scan {key} never happened"
        t_us, codes = truth[key]
        assert (int(r["time64_us"]) & 0xFFFFFFFF) == t_us, key
        assert tuple(int(c) for c in r["codes"]) == codes, key


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far, s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nobody listens on (the system's choice, released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def taken_port() -> Iterator[int]:
    """A TCP port of 127.0.0.1 that a listening socket holds for the ``with`` block."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def write_config(path: Path, url: str, directory: Path, extra: str = "") -> Path:
    path.write_text(
        f'[daq]\nurl = "{url}"\n\n[recording]\ndirectory = "{directory}"\n{extra}',
        encoding="utf-8",
    )
    return path


class NotifySocket:
    """The manager's end of the notify protocol: a unix datagram socket."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.2)
        self.path = path
        self.messages: list[dict[str, str]] = []

    def wait_for(self, key: str, value: str | None = None, timeout: float = 10.0) -> dict:
        deadline = time.monotonic() + timeout
        seen = len(self.messages)
        while time.monotonic() < deadline:
            for m in self.messages[seen:]:
                if key in m and (value is None or m[key] == value):
                    return m
            seen = len(self.messages)
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            self.messages.append(dict(line.split("=", 1) for line in data.decode().splitlines()))
        raise AssertionError(f"no {key}={value} within {timeout} s: {self.messages}")
