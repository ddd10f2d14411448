"""loopcal as real subprocesses (``loopcal record``, ``loopcal daemon``, any command), their
log lines as they come, and what they serve (metrics, the notify socket, ports)."""

from __future__ import annotations

import contextlib
import io
import json
import logging
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

from prometheus_client.parser import text_string_to_metric_families

#: -X faulthandler: a subprocess that does not stop when told is made to say where it is
LOOPCAL = [sys.executable, "-X", "faulthandler", "-m", "loopcal.daemon.cli"]


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
        """SIGTERM; returns (exit status, seconds it took to exit). Not gone within
        ``timeout``: an AssertionError with its log (it is killed)."""
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        try:
            rc = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.send_signal(signal.SIGABRT)  # faulthandler prints every thread's stack
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                pass
            self.kill()
            raise AssertionError(f"still running {timeout:g} s after SIGTERM (its threads' "
                                 f"stacks at SIGABRT last):\n{self.text}") from None
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


def loopcal(
    *args: str | Path, env: dict | None = None, timeout: float = 300
) -> subprocess.CompletedProcess:
    """``loopcal ARGS`` run to its end: its exit status, stdout and stderr (text)."""
    return subprocess.run(
        [*LOOPCAL, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, **(env or {})},
    )


def loopcal_main(*args: str | Path) -> subprocess.CompletedProcess:
    """``loopcal ARGS`` run by :func:`loopcal.daemon.cli.main` in this process, stdout and
    stderr captured: what a subprocess would say, a second sooner.

    For the checks of a command's refusals and output that start nothing (bad input: exit
    2 before anything runs); what a process does as a process (signals, ports, the exit
    status the shell sees, a traceback) stays with :func:`loopcal`. The root logger is
    put back as it was: a command that configures logging must not write into the next
    one's captured stderr.
    """
    from loopcal.daemon.cli import main

    out, err = io.StringIO(), io.StringIO()
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    argv = [str(a) for a in args]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                status = main(argv)
            except SystemExit as exc:  # argparse's refusals and --help
                status = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)
    return subprocess.CompletedProcess([*LOOPCAL, *argv], status, out.getvalue(), err.getvalue())


def fresh_config(path: Path) -> Path:
    """A controller config at ``path`` as ``loopcal init-config`` writes it."""
    proc = loopcal_main("init-config", path, "--force")
    assert proc.returncode == 0, proc.stderr
    return path


def calibrate_json(*args: str | Path) -> tuple[int, dict, str]:
    """``loopcal calibrate ARGS --json``: exit status, its JSON object, stderr."""
    proc = loopcal_main("calibrate", *args, "--json")
    doc = json.loads(proc.stdout) if proc.stdout.strip() else {}
    return proc.returncode, doc, proc.stderr
