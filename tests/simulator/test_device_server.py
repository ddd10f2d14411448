"""The serial transports behind an emulated serial device server (``line="tcp"``): the same
bytes as on the pseudo-terminal line, raw over TCP on 127.0.0.1; the device server stays up
whatever the module does; nothing a client sends breaks it."""

from __future__ import annotations

import socket
import time
from urllib.parse import urlsplit

import pytest
import serial
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from loopcal.simulator.clock import ManualClock
from loopcal.simulator.emulator import Emulator
from loopcal.simulator.testing import LDQ412Options
from tests.support.emulator import ANSWER_S, SILENCE_S, ascii_ask, golden_source
from tests.support.fuzz import examples

SNAPSHOT = "0000 0014 000F 4240 0800 0001 0FFF 0BB8 0204 0015"  # 1 s at 20 Hz
RTU_SNAPSHOT = bytes.fromhex("01 04 0000 000A 700D")
RTU_ANSWER = bytes.fromhex("01 04 14" + SNAPSHOT + "AAD5")
IDENTITY = {"ascii": (b"$01M\r", b"!01LDQ412\r"), "modbus-rtu": (RTU_SNAPSHOT, RTU_ANSWER)}


def line_of(emu: Emulator) -> serial.SerialBase:
    """The emulator's line as a driver opens it: pyserial's socket:// at its host:port."""
    u = urlsplit(emu.url)
    return serial.serial_for_url(f"socket://{u.hostname}:{u.port}", timeout=ANSWER_S)


def ask(port: serial.SerialBase, transport: str, frame: bytes, wait: float = ANSWER_S) -> bytes:
    if transport == "ascii":
        return ascii_ask(port, frame, wait)
    port.reset_input_buffer()
    port.timeout = wait
    port.write(frame)
    return port.read(len(RTU_ANSWER) if frame == RTU_SNAPSHOT else 5)


def test_the_url_names_the_device_servers_address_and_the_lines_settings():
    for transport, query in (("ascii", "baud=115200&addr=01&checksum=0"),
                             ("modbus-rtu", "baud=115200&unit=1")):  # fmt: skip
        with Emulator(transport, golden_source(), clock=ManualClock(), line="tcp") as emu:
            u = urlsplit(emu.url)
            assert (u.scheme, u.hostname, u.port, u.path, u.query) == (
                transport, "127.0.0.1", emu.port, "", query)  # fmt: skip
            assert emu.link is None and emu.port > 0


@pytest.mark.parametrize("transport", ["ascii", "modbus-rtu"])
def test_the_same_frames_get_the_same_bytes_as_on_the_pty(transport):
    clock = ManualClock()
    with Emulator(transport, golden_source(), clock=clock, line="tcp") as emu:
        clock.advance(1.0)
        with line_of(emu) as port:
            if transport == "ascii":
                assert ask(port, transport, b"$01M\r") == b"!01LDQ412\r"
                assert ask(port, transport, b"#014\r") == b">BB8\r"
                assert ask(port, transport, b"#02\r", SILENCE_S) == b""  # another module
                port.write(b"$01R\r#014\r")  # two frames in one write, answered in order
                assert port.read_until(b"\r") == b"!010014\r"
                assert port.read_until(b"\r") == b">BB8\r"
            else:
                assert ask(port, transport, RTU_SNAPSHOT) == RTU_ANSWER
                port.write(bytes.fromhex("01 04 0100 0007 B034"))  # an exception, CRC and all
                assert port.read(5) == bytes.fromhex("01 84 03 0301")


@pytest.mark.parametrize("transport", ["ascii", "modbus-rtu"])
def test_the_device_server_stays_up_while_the_module_is_off_stalled_or_cut_off(transport):
    clock = ManualClock()
    frame, _ = IDENTITY[transport]
    with Emulator(transport, golden_source(), clock=clock, line="tcp") as emu:
        clock.advance(1.0)
        with line_of(emu) as port:
            assert ask(port, transport, frame)
            faults = ((lambda: emu.faults.stall(5.0), lambda: clock.advance(6.0)),
                      (emu.faults.disconnect, emu.faults.reconnect),
                      (lambda: emu.faults.restart(5.0), lambda: clock.advance(6.0)))  # fmt: skip
            for begin, end in faults:
                begin()
                assert ask(port, transport, frame, SILENCE_S) == b""  # silent, still open
                end()
                assert ask(port, transport, frame), "answers again on the same connection"


@pytest.mark.parametrize("transport", ["ascii", "modbus-rtu"])
def test_closing_the_emulator_closes_every_connection(transport):
    emu = Emulator(transport, golden_source(), clock=ManualClock(), line="tcp").start()
    try:
        conns = [socket.create_connection(("127.0.0.1", emu.port), timeout=5) for _ in range(2)]
        time.sleep(0.05)  # let the server accept both
    finally:
        emu.close()
    for c in conns:
        with c:
            assert c.recv(1) == b""  # an orderly close
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", emu.port), timeout=5).close()


def test_a_line_that_is_neither_is_refused_naming_it():
    with pytest.raises(ValueError, match="line must be one of"):
        Emulator("ascii", line="usb")
    with pytest.raises(ValueError, match="ldq412 option line='usb'"):
        LDQ412Options(line="usb")


@pytest.fixture(scope="module")
def served():
    """Both serial protocols behind device servers, for the fuzz test's examples."""
    emus = {t: Emulator(t, golden_source(), clock=ManualClock(), line="tcp").start()
            for t in IDENTITY}  # fmt: skip
    for emu in emus.values():
        emu.clock.advance(1.0)
    yield emus
    for emu in emus.values():
        emu.close()


@settings(max_examples=examples(40), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(transport=st.sampled_from(sorted(IDENTITY)), junk=st.binary(min_size=1, max_size=300),
       hang_up=st.booleans())  # fmt: skip
def test_whatever_a_client_sends_the_next_one_is_answered(served, transport, junk, hang_up):
    emu = served[transport]
    frame, answer = IDENTITY[transport]
    with socket.create_connection(("127.0.0.1", emu.port), timeout=5) as junky:
        junky.sendall(junk)
        if not hang_up:
            junky.settimeout(0.05)
            try:
                while junky.recv(4096):  # whatever it answered, if anything
                    pass
            except TimeoutError:
                pass
    with socket.create_connection(("127.0.0.1", emu.port), timeout=ANSWER_S) as line:
        line.sendall(frame)
        got = b""
        while len(got) < len(answer) and (more := line.recv(len(answer) - len(got))):
            got += more
        assert got == answer
