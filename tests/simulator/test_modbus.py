"""Modbus TCP and RTU on the wire: golden bytes, exceptions, FIFO, unit filtering.

Byte-level checks use a raw socket or raw pyserial; library-level checks use pymodbus'
own clients. Every transport is real: TCP on 127.0.0.1, RTU on pseudo-terminals.
"""

from __future__ import annotations

import socket
import time
from urllib.parse import urlsplit

import pytest
import serial
from pymodbus.client import ModbusSerialClient, ModbusTcpClient

from loopcal.drivers.ldq412 import FIFO_FILLER, join_u32
from loopcal.simulator.clock import ManualClock
from loopcal.simulator.emulator import Emulator
from tests.support.emulator import ANSWER_S, SILENCE_S, golden_source, recv_exact


def tcp_ask(sock: socket.socket, pdu_hex: str, unit: int = 1, tid: int = 0x0101) -> bytes:
    """Send one MBAP frame; return the whole answer frame (raises TimeoutError)."""
    pdu = bytes.fromhex(pdu_hex.replace(" ", ""))
    sock.sendall(
        tid.to_bytes(2, "big")
        + b"\x00\x00"
        + (len(pdu) + 1).to_bytes(2, "big")
        + bytes([unit])
        + pdu
    )
    head = recv_exact(sock, 6)
    return head + recv_exact(sock, int.from_bytes(head[4:6], "big"))


def tcp_pdu(sock: socket.socket, pdu_hex: str) -> str:
    """The answer's PDU (function code onwards) as hex, checking the MBAP header."""
    frame = tcp_ask(sock, pdu_hex)
    assert frame[:4] == b"\x01\x01\x00\x00" and frame[6] == 1
    return frame[7:].hex()


@pytest.fixture
def tcp_emu():
    clock = ManualClock()
    with Emulator("modbus-tcp", golden_source(), clock=clock) as emu:
        emu.test_clock = clock
        yield emu


@pytest.fixture
def tcp_sock(tcp_emu):
    with socket.create_connection((tcp_emu.host, tcp_emu.port), timeout=1.0) as sock:
        yield sock


# ---------------------------------------------------------------- golden bytes


SNAPSHOT_PAYLOAD = "0000 0014 000F 4240 0800 0001 0FFF 0BB8 0204 0015"  # 1 s at 20 Hz


def test_tcp_golden_snapshot_response(tcp_emu, tcp_sock):
    tcp_emu.test_clock.advance(1.0)
    answer = tcp_ask(tcp_sock, "04 0000 000A", tid=0x1234)
    assert answer == bytes.fromhex("1234 0000 0017 01 04 14" + SNAPSHOT_PAYLOAD)


def test_rtu_golden_snapshot_frame_with_crc():
    clock = ManualClock()
    with Emulator("modbus-rtu", golden_source(), clock=clock) as emu:
        assert urlsplit(emu.url).query == "baud=115200&unit=1"
        clock.advance(1.0)
        with serial.Serial(urlsplit(emu.url).path, 115200, timeout=0.5) as port:
            port.write(bytes.fromhex("01 04 0000 000A 700D"))
            answer = port.read(25)
            assert answer == bytes.fromhex("01 04 14" + SNAPSHOT_PAYLOAD + "AAD5")
            # exception frame, CRC included
            port.write(bytes.fromhex("01 04 0100 0007 B034"))
            assert port.read(5) == bytes.fromhex("01 84 03 0301")


# ---------------------------------------------------------------- exceptions


@pytest.mark.parametrize(
    ("request_pdu", "answer_pdu"),
    [
        ("04 0000 000B", "8402"),  # past register 9
        ("04 000A 0001", "8402"),
        ("04 00FF 0001", "8402"),
        ("04 0204 0001", "8402"),  # 516
        ("04 0000 0000", "8403"),  # quantity 0
        ("04 0000 007E", "8403"),  # quantity 126
        ("04 0100 0007", "8403"),  # FIFO window, not N*6
        ("04 0100 0079", "8402"),  # FIFO window, 121 registers
        ("04 0106 0006", "8402"),  # FIFO window, not at its start
        ("03 0000 0006", "8302"),
        ("03 0005 0001", "8302"),
        ("03 0000 0000", "8303"),
        ("06 0000 0000", "8603"),  # scan rate 0
        ("06 0000 00C9", "8603"),  # scan rate 201
        ("06 0001 0003", "8603"),  # oversampling 3
        ("06 0002 0002", "8603"),
        ("06 0004 0002", "8603"),
        ("06 0005 0001", "8602"),
        ("10 0000 0002 04 0064 0003", "9003"),
        ("10 0004 0002 04 0000 0000", "9002"),
        ("01 0000 0001", "8101"),  # coils: not implemented
        ("02 0000 0001", "8201"),
        ("05 0000 FF00", "8501"),
        ("08 0000 1234", "8801"),  # diagnostics
        ("2B 0E 01 00", "ab01"),  # device identification
        ("17 0000 0001 0000 0001 02 0014", "9701"),
        ("41", "c101"),  # unknown function
    ],
)
def test_exception_answers(tcp_emu, tcp_sock, request_pdu, answer_pdu):
    tcp_emu.test_clock.advance(0.5)
    assert tcp_pdu(tcp_sock, request_pdu) == answer_pdu
    # nothing was applied or popped
    assert tcp_pdu(tcp_sock, "03 0000 0005") == "030a" + "0014 0001 0000 0000 0000".replace(" ", "")
    assert tcp_pdu(tcp_sock, "04 0009 0001").endswith("000b")  # 11 scans still waiting


def test_write_single_and_multiple_echo_the_request(tcp_emu, tcp_sock):
    tcp_emu.test_clock.advance(0.5)
    assert tcp_pdu(tcp_sock, "06 0000 0064") == "0600000064"
    assert tcp_pdu(tcp_sock, "06 0002 0001") == "0600020001"  # echo of the command value
    assert tcp_pdu(tcp_sock, "04 0008 0002") == "0404" + "0204" + "0000"  # FIFO cleared
    assert tcp_pdu(tcp_sock, "10 0001 0003 06 0008 0000 0001") == "1000010003"
    assert tcp_pdu(tcp_sock, "03 0000 0005") == "030a" + "0064 0008 0000 0000 0000".replace(" ", "")
    assert tcp_pdu(tcp_sock, "04 0008 0001") == "04020004"  # restart bit cleared


# ---------------------------------------------------------------- FIFO through a client


def test_fifo_drained_by_pymodbus_client_matches_truth():
    with Emulator("modbus-tcp", scan_rate_hz=200, clock=ManualClock(), seed=4) as emu:
        emu.clock.advance(0.5)  # 101 scans
        client = ModbusTcpClient(emu.host, port=emu.port, timeout=1)
        assert client.connect()
        try:
            got = []
            while True:
                level = client.read_input_registers(9, count=1, device_id=1).registers[0]
                if level == 0:
                    break
                regs = client.read_input_registers(256, count=120, device_id=1).registers
                for i in range(0, 120, 6):
                    if regs[i : i + 6] != [FIFO_FILLER] * 6:
                        got.append((join_u32(regs[i], regs[i + 1]), tuple(regs[i + 2 : i + 6])))
            truth = [(s.counter, s.codes) for s in emu.truth]
            assert got == truth
            assert len(got) == 101
            # a drained FIFO answers filler only
            regs = client.read_input_registers(256, count=12, device_id=1).registers
            assert regs == [FIFO_FILLER] * 12
        finally:
            client.close()


def test_rtu_through_pymodbus_client():
    clock = ManualClock()
    with Emulator("modbus-rtu", golden_source(), clock=clock, serial_number=0xDEADBEEF) as emu:
        client = ModbusSerialClient(urlsplit(emu.url).path, baudrate=115200, timeout=0.5)
        assert client.connect()
        try:
            ident = client.read_input_registers(512, count=4, device_id=1).registers
            assert ident == [0x0412, 0x0201, 0xDEAD, 0xBEEF]
            assert not client.write_register(0, 50, device_id=1).isError()
            clock.advance(0.1)
            regs = client.read_input_registers(256, count=30, device_id=1).registers
            assert [join_u32(regs[i], regs[i + 1]) for i in range(0, 30, 6)] == [0, 1, 2, 3, 4]
            assert regs[26:30] == [2048, 1, 4095, 3000]  # counter 4's codes
            exc = client.read_input_registers(256, count=7, device_id=1)
            assert exc.isError() and exc.exception_code == 3
        finally:
            client.close()


# ---------------------------------------------------------------- addressing


def test_tcp_other_unit_gets_no_answer(tcp_emu, tcp_sock):
    tcp_sock.settimeout(SILENCE_S)
    with pytest.raises(TimeoutError):
        tcp_ask(tcp_sock, "04 0000 000A", unit=2)
    with pytest.raises(TimeoutError):
        tcp_ask(tcp_sock, "04 0000 000A", unit=0)  # broadcast is ignored
    tcp_sock.settimeout(1.0)
    assert tcp_pdu(tcp_sock, "04 0009 0001") == "04020001"  # nothing popped, still served


def test_rtu_ignores_other_units_and_bad_crc():
    with Emulator("modbus-rtu", golden_source(), clock=ManualClock(), unit=7) as emu:
        assert emu.url.endswith("unit=7")
        with serial.Serial(urlsplit(emu.url).path, 115200, timeout=SILENCE_S) as port:
            port.write(bytes.fromhex("01 04 0000 000A 700D"))  # unit 1
            assert port.read(64) == b""
            port.write(bytes.fromhex("07 04 0009 0001 00") + b"\x00")  # bad CRC
            assert port.read(64) == b""
            port.timeout = ANSWER_S  # an answer now: read as soon as its 7 bytes came
            port.write(bytes.fromhex("07 04 0009 0001 E1AE"))
            assert port.read(7) == bytes.fromhex("07 04 02 0001 F0F0")


# ---------------------------------------------------------------- consistency


def test_snapshot_never_mixes_two_scans_at_200hz_real_time():
    with Emulator("modbus-tcp", scan_rate_hz=200, seed=11) as emu:
        client = ModbusTcpClient(emu.host, port=emu.port, timeout=1)
        assert client.connect()
        seen = []
        try:
            # until the snapshot moved on over 10 scans while it was read (at 200 Hz, about
            # 0.06 s; the deadline only ends a module whose snapshot never moves)
            deadline = time.monotonic() + 20
            while len({join_u32(r[0], r[1]) for r in seen}) <= 10 or len(seen) <= 20:
                assert time.monotonic() < deadline, seen[-1:]
                seen.append(client.read_input_registers(0, count=10, device_id=1).registers)
        finally:
            client.close()
        truth = {s.counter: s for s in emu.truth}
        counters = set()
        for regs in seen:
            scan = truth[join_u32(regs[0], regs[1])]
            assert join_u32(regs[2], regs[3]) == scan.time_us
            assert tuple(regs[4:8]) == scan.codes
            counters.add(scan.counter)
        assert len(counters) > 10  # the snapshot moved on while we read
        assert len(seen) > 20
