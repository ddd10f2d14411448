"""Injected faults, seen on real wires (TCP sockets, pty serial lines)."""

from __future__ import annotations

import socket
import time
from urllib.parse import urlsplit

import pytest
import serial
from pymodbus.framer.rtu import FramerRTU

from loopcal.simulator.clock import ManualClock
from loopcal.simulator.emulator import Emulator
from tests.support.emulator import ANSWER_S, SILENCE_S, ascii_ask, golden_source, recv_exact


def tcp_ask(sock: socket.socket, pdu_hex: str, tid: int = 0x0101) -> bytes:
    pdu = bytes.fromhex(pdu_hex.replace(" ", ""))
    sock.sendall(
        tid.to_bytes(2, "big") + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big") + b"\x01" + pdu
    )
    head = recv_exact(sock, 6)
    return head + recv_exact(sock, int.from_bytes(head[4:6], "big"))


def connect(emu: Emulator, timeout: float = 1.0) -> socket.socket:
    return socket.create_connection((emu.host, emu.port), timeout=timeout)


def connect_when_back(emu: Emulator, within_s: float = 1.0) -> socket.socket:
    """Connect, retrying while the module refuses (its listener follows power state
    on a 10 ms housekeeping tick)."""
    deadline = time.monotonic() + within_s
    while True:
        try:
            return connect(emu)
        except ConnectionRefusedError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.01)


def assert_reset(sock: socket.socket) -> None:
    """The peer reset the connection (RST), rather than closing it or staying silent."""
    sock.settimeout(1.0)
    with pytest.raises(ConnectionResetError):
        sock.sendall(bytes.fromhex("0101 0000 0006 01 04 0009 0001"))
        sock.recv(64)


def level(sock: socket.socket) -> int:
    return int.from_bytes(tcp_ask(sock, "04 0009 0001")[-2:], "big")


def serial_port(emu: Emulator, timeout: float = SILENCE_S) -> serial.Serial:
    return serial.Serial(urlsplit(emu.url).path, 115200, timeout=timeout)


# ---------------------------------------------------------------- link


def test_tcp_disconnect_resets_refuses_and_keeps_scanning():
    clock = ManualClock()
    with Emulator("modbus-tcp", golden_source(), clock=clock) as emu:
        sock = connect(emu)
        assert level(sock) == 1
        emu.faults.disconnect()
        assert_reset(sock)
        with pytest.raises(ConnectionRefusedError):
            connect(emu)
        clock.advance(1.0)  # the module scans on, unread
        emu.faults.reconnect()
        with connect(emu) as sock2:
            assert level(sock2) == 21
        sock.close()


def test_serial_disconnect_loses_requests_both_ways():
    with Emulator("modbus-rtu", golden_source(), clock=ManualClock()) as emu:
        with serial_port(emu) as port:
            emu.faults.disconnect()
            port.write(bytes.fromhex("01 04 0100 0006 71F4"))  # would pop a scan
            assert port.read(64) == b""
            link = emu.link
            assert link is not None
            deadline = time.monotonic() + ANSWER_S
            while link.bytes_lost < 8:  # the cut cable took it (not merely late)
                assert time.monotonic() < deadline, link.bytes_lost
                time.sleep(0.01)
            emu.faults.reconnect()
            port.timeout = ANSWER_S  # an answer now: read as soon as its 7 bytes came
            port.write(bytes.fromhex("01 04 0009 0001 E1C8"))
            assert port.read(7) == bytes.fromhex("01 04 02 0001 78F0")  # nothing was popped


def test_stall_ignores_requests_for_device_time():
    clock = ManualClock()
    with Emulator("modbus-tcp", golden_source(), clock=clock) as emu, connect(emu) as sock:
        emu.faults.stall(1.0)
        sock.settimeout(SILENCE_S)
        with pytest.raises(TimeoutError):
            tcp_ask(sock, "04 0100 0006")  # a FIFO pop that must not happen
        clock.advance(0.5)
        with pytest.raises(TimeoutError):
            tcp_ask(sock, "04 0009 0001")
        clock.advance(0.5)
        sock.settimeout(1.0)
        assert level(sock) == 21  # scans went on, none was popped


# ---------------------------------------------------------------- power cycle


def test_restart_tcp_silent_refused_then_reset_and_power_on_state():
    clock = ManualClock()
    with Emulator("modbus-tcp", golden_source(), clock=clock, scan_rate_hz=20) as emu:
        sock = connect(emu)
        tcp_ask(sock, "10 0000 0004 08 0064 0004 0000 0001")  # 100 Hz, x4, clear restart
        clock.advance(1.0)
        emu.faults.restart()
        sock.settimeout(SILENCE_S)
        with pytest.raises(TimeoutError):
            tcp_ask(sock, "04 0000 000A")  # off: established connection is silent
        with pytest.raises(ConnectionRefusedError):
            connect(emu)
        clock.advance(1.999)
        time.sleep(0.05)
        with pytest.raises(ConnectionRefusedError):
            connect(emu)
        clock.advance(0.001)
        with connect_when_back(emu) as sock2:
            answer = tcp_ask(sock2, "04 0000 000A")
            assert answer[9:].hex() == "0000 0000 0000 0000 0800 0001 0fff 0bb8 0204 0001".replace(
                " ", ""
            )
            assert tcp_ask(sock2, "03 0000 0005")[9:].hex() == "00140001000000000000"
        assert_reset(sock)  # the rebooted module forgot the old connection
        sock.close()
        boots = [s.boot for s in emu.truth]
        assert boots.count(1) == 1 and boots[-1] == 1


def test_restart_ascii_is_silent_for_two_device_seconds():
    clock = ManualClock()
    with Emulator("ascii", golden_source(), clock=clock) as emu, serial_port(emu) as port:
        assert ascii_ask(port, b"#011\r") == b">800\r"
        clock.advance(1.0)
        emu.faults.restart()
        assert ascii_ask(port, b"#01\r", SILENCE_S) == b""
        clock.advance(1.999)
        assert ascii_ask(port, b"#01\r", SILENCE_S) == b""
        clock.advance(0.001)
        answer = ascii_ask(port, b"#01\r")
        assert int(answer[1:9], 16) == 0 and int(answer[-5:-1], 16) & 0x0200  # restart bit
        assert emu.truth[-1].boot == 1


# ---------------------------------------------------------------- bytes on the wire


def test_garbage_goes_out_before_the_next_answer_only():
    with Emulator("modbus-rtu", golden_source(), clock=ManualClock(), seed=3) as emu:
        with serial_port(emu) as port:
            clean = bytes.fromhex("01 04 02 0001 78F0")
            emu.faults.garbage(5)
            port.write(bytes.fromhex("01 04 0009 0001 E1C8"))
            answer = port.read(64)
            assert len(answer) == 5 + len(clean) and answer.endswith(clean)
            port.write(bytes.fromhex("01 04 0009 0001 E1C8"))
            assert port.read(64) == clean
        with Emulator("modbus-rtu", golden_source(), clock=ManualClock(), seed=3) as emu2:
            with serial_port(emu2) as port:
                emu2.faults.garbage(5)
                port.write(bytes.fromhex("01 04 0009 0001 E1C8"))
                assert port.read(64) == answer  # seeded: same junk


def test_corrupt_next_breaks_rtu_crc_n_times():
    with Emulator("modbus-rtu", golden_source(), clock=ManualClock()) as emu:
        with serial_port(emu) as port:
            emu.faults.corrupt_next(2)
            frames = []
            port.timeout = ANSWER_S  # three answers: each read as soon as its 7 bytes came
            for _ in range(3):
                port.write(bytes.fromhex("01 04 0009 0001 E1C8"))
                frames.append(port.read(7))
            crc_ok = [FramerRTU.check_CRC(f[:-2], int.from_bytes(f[-2:], "big")) for f in frames]
            assert crc_ok == [False, False, True]
            assert frames[0][:-2] == frames[2][:-2]  # only the CRC is broken


def test_corrupt_next_breaks_tcp_mbap():
    with Emulator("modbus-tcp", golden_source(), clock=ManualClock()) as emu, connect(emu) as s:
        emu.faults.corrupt_next()
        bad = tcp_ask(s, "04 0009 0001")
        good = tcp_ask(s, "04 0009 0001")
        assert good == bytes.fromhex("0101 0000 0005 01 04 02 0001")
        assert bad == bytes.fromhex("0101 0001 0005 01 04 02 0001")  # protocol id 1


def test_corrupt_next_breaks_ascii_with_and_without_checksum():
    with Emulator("ascii", golden_source(), clock=ManualClock()) as emu:
        with serial_port(emu) as port:
            emu.faults.corrupt_next()
            assert ascii_ask(port, b"$01M\r") == b"!p1LDQ412\r"  # '0' ^ 0x40: not hex
            with emu.handle.synced() as device:
                device.write_registers(4, [1])
            emu.faults.corrupt_next()
            assert ascii_ask(port, b"$01MD2\r") == b"!01LDQ412FB\r"  # sum is FA
            assert ascii_ask(port, b"$01MD2\r") == b"!01LDQ412FA\r"


# ---------------------------------------------------------------- channels


def test_channel_faults_and_clear_over_ascii():
    clock = ManualClock()
    with Emulator("ascii", golden_source(), clock=clock) as emu, serial_port(emu) as port:
        emu.faults.stuck_channel(1, 0x123)
        emu.faults.sensor_fault(2, True)
        emu.faults.saturate(3, "low")
        emu.faults.saturate(4, "high")
        clock.advance(0.05)
        answer = ascii_ask(port, b"#01\r")
        assert answer[17:] == b"123FFF000FFF022E\r"  # fault ch2; rail ch2..4; restart
        emu.faults.stall(10.0)
        emu.faults.garbage(3)
        emu.faults.corrupt_next(4)
        emu.faults.clear()
        clock.advance(0.05)
        assert ascii_ask(port, b"#01\r")[17:] == b"800001FFFBB80204\r"


def test_clear_reconnects_tcp():
    with Emulator("modbus-tcp", golden_source(), clock=ManualClock()) as emu:
        emu.faults.disconnect()
        with pytest.raises(ConnectionRefusedError):
            connect(emu)
        emu.faults.clear()
        with connect(emu) as sock:
            assert level(sock) == 1
