"""Real things at an address that are not the module: TCP servers of other protocols (an
echo, an HTTP server, one that closes at once, one that never answers), a listener whose
queue is full (a host that does not answer), a Modbus device of another model, a relay
that lets a test act between a host's requests, a serial line where another device talks,
and a process that holds a serial port."""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from loopcal.simulator.pty import PtyLink

from .emulator import recv_exact

#: what the HTTP server answers to anything
HTTP_ANSWER = b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"


@contextmanager
def tcp_server(kind: str | Callable[[bytearray], bytes]) -> Iterator[int]:
    """A TCP server on 127.0.0.1 that speaks no Modbus TCP; yields its port.

    kind: ``echo`` (sends back what it gets), ``http`` (answers 400 and closes), ``close``
    (closes every connection at its first bytes), ``silent`` (reads, never answers), or a
    function that answers a connection's bytes so far (a module on a serial device
    server's line): it takes what it answers off the buffer and returns the answer.
    """
    listener = socket.create_server(("127.0.0.1", 0))
    conns: list[socket.socket] = []

    def serve(conn: socket.socket) -> None:
        buffer = bytearray()
        with conn:
            while data := _recv(conn):
                if callable(kind):
                    buffer += data
                    conn.sendall(kind(buffer))
                elif kind == "echo":
                    conn.sendall(data)
                elif kind == "http":
                    conn.sendall(HTTP_ANSWER)
                    return
                elif kind == "close":
                    return

    def accept() -> None:
        while True:
            try:
                conn, _ = listener.accept()
            except OSError:
                return
            conns.append(conn)
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    threading.Thread(target=accept, daemon=True).start()
    try:
        yield listener.getsockname()[1]
    finally:
        with contextlib.suppress(OSError):
            listener.shutdown(socket.SHUT_RDWR)  # wakes accept(): close() alone does not
        listener.close()
        for conn in conns:
            conn.close()


def _recv(conn: socket.socket) -> bytes:
    try:
        return conn.recv(4096)
    except OSError:
        return b""


@contextmanager
def unanswered_port() -> Iterator[int]:
    """A port of 127.0.0.1 whose listener's queue is full: the kernel drops further SYNs,
    so a connection neither succeeds nor is refused (a host that does not answer)."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen(0)
    port = listener.getsockname()[1]
    fillers = []
    for _ in range(4):  # the queue holds backlog + 1; more make sure it is full
        c = socket.socket()
        c.setblocking(False)
        try:
            c.connect(("127.0.0.1", port))
        except BlockingIOError:
            pass
        fillers.append(c)
    time.sleep(0.05)  # the handshakes that can complete have
    try:
        yield port
    finally:
        for c in fillers:
            c.close()
        listener.close()


@contextmanager
def other_modbus_device(model_code: int | None) -> Iterator[int]:
    """A Modbus TCP device (pymodbus' own server), unit 1, that is not an LDQ-412: input
    registers 512-515 hold ``model_code``, firmware 1.00 and serial 7, or (None) do not
    exist (a read there answers exception 02). Yields its port."""
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    regs = DataType.REGISTERS
    inputs = [SimData(0, count=10, datatype=regs)]
    if model_code is not None:
        inputs.append(SimData(512, values=[model_code, 0x0100, 0, 7], datatype=regs))
    bits = [SimData(0, values=False, datatype=DataType.BITS)]
    device = SimDevice(id=1, simdata=(bits, bits, [SimData(0, values=[20] * 5, datatype=regs)],
                                      inputs))  # fmt: skip
    loop = asyncio.new_event_loop()
    started = threading.Event()
    box: dict = {}

    async def main() -> None:
        server = ModbusTcpServer(device, address=("127.0.0.1", 0))
        await server.serve_forever(background=True)
        box["server"] = server
        box["port"] = server.transport.sockets[0].getsockname()[1]
        box["stop"] = asyncio.Event()
        started.set()
        await box["stop"].wait()
        await server.shutdown()

    thread = threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True)
    thread.start()
    assert started.wait(10), "pymodbus' server did not start"
    try:
        yield box["port"]
    finally:
        loop.call_soon_threadsafe(box["stop"].set)
        thread.join(10)


@contextmanager
def modbus_tcp_relay(host: str, port: int, before: Callable[[bytes], None]) -> Iterator[int]:
    """A Modbus TCP relay on 127.0.0.1 to ``host:port`` for one host connection; yields
    its port. ``before(pdu)`` runs before each request is passed on, so a test can act at
    an exact point between a host's requests (another master reading, say)."""
    listener = socket.create_server(("127.0.0.1", 0))
    upstream = socket.create_connection((host, port), timeout=10)

    def frame(conn: socket.socket) -> bytes:
        head = recv_exact(conn, 7)  # MBAP: id, protocol, length, unit
        return head + recv_exact(conn, int.from_bytes(head[4:6], "big") - 1)

    def relay() -> None:
        try:
            conn, _ = listener.accept()
        except OSError:
            return
        with conn, contextlib.suppress(OSError):  # either side closed: the relay ends
            while request := frame(conn):
                before(request[7:])
                upstream.sendall(request)
                conn.sendall(frame(upstream))

    thread = threading.Thread(target=relay, daemon=True)
    thread.start()
    try:
        yield listener.getsockname()[1]
    finally:
        listener.close()
        upstream.close()
        thread.join(10)


@contextmanager
def running_link(baud: int) -> Iterator[PtyLink]:
    """A bare null-modem pty link (:class:`~loopcal.simulator.pty.PtyLink`) whose module
    side is at ``baud``, relaying on a loop of its own; closed after."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    link = PtyLink(baud)
    started = threading.Event()
    loop.call_soon_threadsafe(lambda: (link.start(loop, lambda: True), started.set()))
    assert started.wait(5)
    try:
        yield link
    finally:
        done = threading.Event()
        loop.call_soon_threadsafe(lambda: (link.close(), done.set()))
        done.wait(5)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.close()


@contextmanager
def talking_line(baud: int, text: bytes, period_s: float = 0.02) -> Iterator[str]:
    """A serial line where another device talks (``text`` every ``period_s``, at ``baud``):
    a pty link whose far side writes on its own; yields the path a host opens."""
    with running_link(baud) as link:
        stop = threading.Event()

        def talk() -> None:
            while not stop.wait(period_s):
                try:
                    os.write(link.device_fd, text)
                except OSError:
                    return

        talker = threading.Thread(target=talk, daemon=True)
        talker.start()
        try:
            yield link.host_path
        finally:
            stop.set()
            talker.join(5)


@contextmanager
def port_holder(path: str) -> Iterator[int]:
    """Another process that opens a serial port exclusively (as pyserial, minicom or a
    driver does) and keeps it; yields its pid once it holds it."""
    code = ("import serial, sys; p = serial.Serial(sys.argv[1], exclusive=True); "
            "print('held', flush=True); sys.stdin.read()")  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", code, path], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
        yield proc.pid
    finally:
        proc.kill()
        proc.wait(10)
