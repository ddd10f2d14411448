"""Starting, stopping and determinism of the emulator as a whole."""

from __future__ import annotations

import contextlib
import os
import socket
import threading
import time
from collections.abc import Callable
from urllib.parse import urlsplit

import pytest
import serial

from loopcal.simulator.clock import ManualClock, RealClock
from loopcal.simulator.emulator import Emulator
from loopcal.simulator.source import ConstantSource
from tests.support.emulator import ANSWER_S, SILENCE_S

TRANSPORTS = ("modbus-tcp", "modbus-rtu", "ascii")


def open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def emulator_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("ldq412-emulator")]


def wait_answers(emu: Emulator, n: int) -> None:
    deadline = time.monotonic() + 2.0
    while emu.wire.answers_sent < n:
        assert time.monotonic() < deadline, "no answer"
        time.sleep(0.001)


def exchange(emu: Emulator, requests: list[bytes]) -> bytes:
    """Send raw requests one at a time, each answered before the clock moves on;
    return every byte that came back (all the emulator sent, then SILENCE_S of nothing)."""
    got = b""
    clock = emu.clock
    assert isinstance(clock, ManualClock)

    def read_all(read: Callable[[], bytes]) -> None:
        nonlocal got
        deadline = time.monotonic() + ANSWER_S
        while len(got) < emu.wire.bytes_sent:
            assert time.monotonic() < deadline, (len(got), emu.wire.bytes_sent)
            with contextlib.suppress(TimeoutError):
                got += read()

    if emu.transport == "modbus-tcp":
        with socket.create_connection((emu.host, emu.port), timeout=SILENCE_S) as sock:
            for k, req in enumerate(requests, start=1):
                sock.sendall(req)
                wait_answers(emu, k)
                read_all(lambda: sock.recv(4096))
                clock.advance(0.37)
            with pytest.raises(TimeoutError):
                got += sock.recv(4096)
        return got
    with serial.Serial(urlsplit(emu.url).path, 115200, timeout=SILENCE_S) as port:
        for k, req in enumerate(requests, start=1):
            port.write(req)
            wait_answers(emu, k)
            read_all(lambda: port.read(4096))
            clock.advance(0.37)
        assert port.read(4096) == b""
    return got


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_starts_fast_and_closes_without_leaking_threads_or_fds(transport):
    fds_before = open_fds()
    threads_before = emulator_threads()
    started = time.monotonic()
    emu = Emulator(transport, scan_rate_hz=200).start()
    startup = time.monotonic() - started
    assert startup < 0.5
    assert emu.running and len(emulator_threads()) == len(threads_before) + 1
    # something is reachable at the url
    if transport == "modbus-tcp":
        socket.create_connection((emu.host, emu.port), timeout=1).close()
    else:
        serial.Serial(urlsplit(emu.url).path, 115200).close()
    emu.close()
    emu.close()  # idempotent
    assert not emu.running
    assert emulator_threads() == threads_before
    assert open_fds() == fds_before


def test_tcp_port_is_released_on_close_and_reported_in_url():
    with Emulator("modbus-tcp") as emu:
        assert emu.url == f"modbus-tcp://127.0.0.1:{emu.port}?unit=1"
        port = emu.port
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=1)
    with Emulator("modbus-tcp", port=port) as again:  # the same fixed port can be reused
        assert again.port == port


def test_start_failure_raises_and_leaks_nothing():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        threads_before = emulator_threads()
        emu = Emulator("modbus-tcp", port=busy.getsockname()[1])
        with pytest.raises(RuntimeError):
            emu.start()
        assert emulator_threads() == threads_before


def test_scans_run_on_their_own_with_the_real_clock():
    clock = RealClock()
    # the module is switched on when it is made, at an instant between these clock reads
    # (not at the clock's 0: a loaded machine took 0.7 ms, a scan of 200 Hz, in between)
    on_from = clock.now()
    emu = Emulator("modbus-tcp", scan_rate_hz=200, clock=clock)
    on_until = clock.now()
    with emu:
        time.sleep(0.3)
        # a read of emu.truth syncs the module to its clock: one scan per 5 ms from its
        # power-on up to an instant between these two clock reads, whatever the load
        before = clock.now()
        truth = emu.truth
        after = clock.now()
        n, counters = len(truth), [s.counter for s in truth]
    assert n >= 50  # nobody read: the module scanned on its own
    assert int((before - on_until) * 200) + 1 <= n <= int((after - on_from) * 200) + 1
    assert counters == list(range(n))


def test_context_manager_and_constructor_validation():
    with pytest.raises(ValueError):
        Emulator("modbus-udp")
    with pytest.raises(ValueError):
        Emulator("modbus-tcp", unit=0)
    with pytest.raises(ValueError):
        Emulator("modbus-tcp", scan_rate_hz=201)
    emu = Emulator("ascii", ConstantSource([0.0] * 4), clock=ManualClock())
    assert emu.url == ""  # not started
    with emu as same:
        assert same is emu and emu.url.startswith("ascii:///dev/pts/")
    assert not emu.running


MODBUS_SESSION = [
    bytes.fromhex("0001 0000 0006 01 04 0000 000A"),
    bytes.fromhex("0002 0000 0006 01 04 0100 0078"),
    bytes.fromhex("0003 0000 0006 01 06 0001 0004"),
    bytes.fromhex("0004 0000 0006 01 04 0100 0078"),
    bytes.fromhex("0005 0000 0006 01 04 0100 0007"),
]
RTU_SESSION = [
    bytes.fromhex("01 04 0000 000A 700D"),
    bytes.fromhex("01 04 0100 0078 F1D4"),
    bytes.fromhex("01 04 0100 0078 F1D4"),
]
ASCII_SESSION = [b"#01\r", b"#012\r", b"%01R0064\r", b"#01\r", b"#01\r"]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("transport", "session"),
    [("modbus-tcp", MODBUS_SESSION), ("modbus-rtu", RTU_SESSION), ("ascii", ASCII_SESSION)],
)
def test_same_seed_and_requests_give_the_same_bytes(transport, session):
    def run(seed: int) -> bytes:
        with Emulator(transport, clock=ManualClock(), seed=seed, scan_rate_hz=50) as emu:
            emu.faults.garbage(4)
            return exchange(emu, session)

    first, second, other = run(9), run(9), run(10)
    assert len(first) > 60
    assert first == second
    assert first != other
