"""The systemd notify protocol against real unix datagram sockets."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import uuid

import pytest

from daemon.sdnotify import Notifier


def bind(address: str) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(address)
    s.settimeout(5)
    return s


def fields(sock: socket.socket) -> dict[str, str]:
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
    assert got["RELOADING"] == "1"
    assert abs(int(got["MONOTONIC_USEC"]) - time.monotonic_ns() // 1000) < 2_000_000
    assert n.stopping("bye") and fields(sock) == {"STOPPING": "1", "STATUS": "bye"}
    n.close()
    sock.close()


def test_outside_systemd_every_call_is_a_no_op():
    n = Notifier(environ={})
    assert not n.enabled and n.watchdog_interval is None
    assert n.ready("x") is False and n.watchdog() is False


def test_a_socket_that_is_gone_is_not_an_error(tmp_path):
    n = Notifier(environ={"NOTIFY_SOCKET": str(tmp_path / "nobody")})
    assert n.ready() is False and n.status("still fine") is False


@pytest.mark.parametrize(
    ("env", "interval"),
    [
        ({"WATCHDOG_USEC": "30000000"}, 15.0),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())}, 15.0),
        ({"WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid() + 1)}, None),
        ({"WATCHDOG_USEC": "soon"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({}, None),
    ],
)
def test_watchdog_interval(env, interval):
    assert Notifier(environ={"NOTIFY_SOCKET": "/x", **env}).watchdog_interval == interval


def test_a_child_process_notifies_from_its_environment(tmp_path):
    sock = bind(str(tmp_path / "notify"))
    code = "from daemon.sdnotify import Notifier; Notifier().ready('hello from the child')"
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify")}
    subprocess.run([sys.executable, "-c", code], env=env, check=True, timeout=60)
    assert fields(sock) == {"READY": "1", "STATUS": "hello from the child"}
