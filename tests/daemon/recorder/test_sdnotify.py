"""The systemd notify protocol against real unix datagram sockets (no mocks)."""

from __future__ import annotations

import logging
import os
import socket
import subprocess
import sys
import time
import uuid

import pytest

from loopcal.daemon.recorder.sdnotify import Notifier
from tests.support import ROOT


def bind(address: str) -> socket.socket:
    """The manager's end: a unix datagram socket bound to ``address``."""
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(address)
    s.settimeout(5)
    return s


def fields(sock: socket.socket) -> dict[str, str]:
    """The next datagram, parsed as systemd does: one KEY=value per line."""
    return dict(line.split("=", 1) for line in sock.recv(4096).decode().splitlines())


@pytest.mark.parametrize("kind", ["path", "abstract"])
def test_messages_arrive_as_systemd_reads_them(tmp_path, kind):
    if kind == "path":
        address = name = str(tmp_path / "notify")
    else:
        name = f"@loopcal-test-{uuid.uuid4().hex}"
        address = "\0" + name[1:]
    sock = bind(address)
    n = Notifier(environ={"NOTIFY_SOCKET": name})
    assert n.enabled
    assert n.ready("starting\nup") and fields(sock) == {"READY": "1", "STATUS": "starting up"}
    assert n.status("x" * 5000) and len(fields(sock)["STATUS"]) == 1000
    assert n.watchdog() and fields(sock) == {"WATCHDOG": "1"}
    assert n.reloading()
    got = fields(sock)
    assert got["RELOADING"] == "1" and set(got) == {"RELOADING", "MONOTONIC_USEC"}
    assert abs(int(got["MONOTONIC_USEC"]) - time.monotonic_ns() // 1000) < 2_000_000
    assert n.stopping("bye") and fields(sock) == {"STOPPING": "1", "STATUS": "bye"}
    assert n.send(STATUS="a\nb", ERRNO=5) and fields(sock) == {"STATUS": "a b", "ERRNO": "5"}
    n.close()
    n.close()  # idempotent
    assert n.watchdog() and fields(sock) == {"WATCHDOG": "1"}  # reopens
    n.close()
    sock.close()


def test_an_explicit_socket_path_wins_over_the_environment(tmp_path):
    sock = bind(str(tmp_path / "mine"))
    n = Notifier(str(tmp_path / "mine"), environ={"NOTIFY_SOCKET": str(tmp_path / "other")})
    assert n.ready() and fields(sock) == {"READY": "1"}
    n.close()
    sock.close()


def test_outside_systemd_every_call_is_a_no_op(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    for n in (Notifier(), Notifier(environ={}), Notifier(environ={"NOTIFY_SOCKET": ""})):
        assert not n.enabled and n.watchdog_interval is None
        assert n.ready("x") is False and n.status("x") is False and n.watchdog() is False
        assert n.reloading() is False and n.stopping() is False and n.send(X=1) is False
        n.close()


def test_a_relative_socket_path_is_refused_not_guessed(caplog):
    with caplog.at_level(logging.WARNING, logger="loopcal.daemon.recorder.sdnotify"):
        n = Notifier(environ={"NOTIFY_SOCKET": "notify.sock"})
    assert not n.enabled and n.ready() is False
    assert "neither an absolute path nor @name" in caplog.text


def test_a_socket_that_is_gone_fails_quietly_and_warns_once(tmp_path, caplog):
    n = Notifier(environ={"NOTIFY_SOCKET": str(tmp_path / "nobody")})
    assert n.enabled
    with caplog.at_level(logging.WARNING, logger="loopcal.daemon.recorder.sdnotify"):
        assert n.ready() is False and n.status("still fine") is False and n.watchdog() is False
    warnings = [r for r in caplog.records if r.name == "loopcal.daemon.recorder.sdnotify"]
    assert len(warnings) == 1 and "nobody" in warnings[0].getMessage()


def test_a_manager_that_does_not_read_never_blocks_the_sender(tmp_path):
    sock = bind(str(tmp_path / "notify"))
    n = Notifier(str(tmp_path / "notify"))
    t0 = time.monotonic()
    results = [n.watchdog() for _ in range(10_000)]  # the queue holds far fewer
    assert time.monotonic() - t0 < 10 and results[0] and not results[-1]
    sock.settimeout(0.1)
    while True:  # drain: sending works again
        try:
            sock.recv(4096)
        except TimeoutError:
            break
    assert n.watchdog() and fields(sock) == {"WATCHDOG": "1"}
    n.close()
    sock.close()


@pytest.mark.parametrize(
    ("env", "interval"),
    [
        ({"WATCHDOG_USEC": "30000000"}, 15.0),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())}, 15.0),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": ""}, 15.0),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid() + 1)}, None),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": "me"}, None),
        ({"WATCHDOG_USEC": "soon"}, None),
        ({"WATCHDOG_USEC": "1.5e6"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "-5"}, None),
        ({}, None),
    ],
)
def test_watchdog_interval(env, interval):
    assert Notifier(environ={"NOTIFY_SOCKET": "/x", **env}).watchdog_interval == interval


def test_a_malformed_watchdog_is_a_warning_not_an_error(caplog):
    with caplog.at_level(logging.WARNING, logger="loopcal.daemon.recorder.sdnotify"):
        n = Notifier(environ={"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "soon"})
    assert n.watchdog_interval is None and "WATCHDOG_USEC='soon'" in caplog.text


def test_no_watchdog_without_a_socket_to_feed_it():
    assert Notifier(environ={"WATCHDOG_USEC": "30000000"}).watchdog_interval is None


def test_a_child_process_notifies_from_its_environment(tmp_path):
    sock = bind(str(tmp_path / "notify"))
    code = (
        "import sys; from loopcal.daemon.recorder.sdnotify import Notifier; n = Notifier(); "
        "sys.exit(0 if n.ready('hello from the child') and n.watchdog_interval == 15.0 else 3)"
    )
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify"), "WATCHDOG_USEC": "30000000"}
    env.pop("WATCHDOG_PID", None)
    subprocess.run([sys.executable, "-c", code], env=env, cwd=ROOT, check=True, timeout=60)
    assert fields(sock) == {"READY": "1", "STATUS": "hello from the child"}
    sock.close()
