"""A module's serial line behind a serial device server in raw TCP mode (a Moxa NPort's "TCP
server" mode): ``ascii://HOST:PORT`` and ``modbus-rtu://HOST:PORT``, opened as pyserial's
``socket://HOST:PORT``.

The device server is a TCP server of this test on 127.0.0.1 (tests.support.servers) whose
answers to the frames the driver sends are a module's behind one: the ASCII protocol's, or
Modbus RTU's (CRC and all). Nothing is mocked: the drivers open a real TCP connection
through pyserial. (The URL's parts are tested in test_units.py, a device server that
refuses in test_probe.py.)
"""

from __future__ import annotations

import time

import pytest
import serial
from pymodbus.framer import FramerRTU
from pymodbus.pdu import DecodePDU
from pymodbus.pdu.register_message import ReadInputRegistersRequest

from loopcal.drivers import ldq412, open_daq, parse_url
from loopcal.drivers.ascii import AsciiDAQ, encode_command
from loopcal.drivers.diagnosis import endpoint
from loopcal.drivers.lines import bytes_waiting
from loopcal.drivers.probe import probe
from loopcal.simulator.clock import ManualClock
from loopcal.simulator.emulator import Emulator
from tests.support.servers import tcp_server

pytestmark = pytest.mark.timeout(60)

#: the ASCII module's answers (address 01, checksum off) to the frames it knows
ASCII_ANSWERS = {
    b"$01M": b"!01LDQ412",
    b"$01F": b"!012.01",
    b"$01R": b"!010014",  # 20 Hz
    # scan 5 at 10 ms, channels 0x800, 0x801, 0x7FF, 0x400, status clear
    b"#01": b">0000000500002710" + b"8008017FF400" + b"0000",
}
#: the Modbus module's registers (unit 1): (function, address) -> value
RTU_REGISTERS = {
    **{
        (4, ldq412.IR_MODEL + i): v
        for i, v in enumerate((ldq412.MODEL_CODE, 0x0201, 0x00C0, 0xFFEE))
    },
    **{(4, i): v for i, v in enumerate((0, 5, 0, 10000, 0x800, 0x801, 0x7FF, 0x400, 0, 0))},
    (3, ldq412.HR_SCAN_RATE): 20,
}


def ascii_module(buffer: bytearray) -> bytes:
    """The answers to the whole ASCII frames in ``buffer`` (taken off it)."""
    out = b""
    while (cr := buffer.find(b"\r")) >= 0:
        frame = bytes(buffer[:cr])
        del buffer[: cr + 1]
        if frame in ASCII_ANSWERS:
            out += ASCII_ANSWERS[frame] + b"\r"
    return out


def rtu_module(buffer: bytearray) -> bytes:
    """The answers to the whole Modbus RTU read requests in ``buffer`` (taken off it)."""
    out = b""
    while len(buffer) >= 8:
        request = bytes(buffer[:8])
        del buffer[:8]
        unit, fc = request[0], request[1]
        address, count = int.from_bytes(request[2:4]), int.from_bytes(request[4:6])
        regs = [RTU_REGISTERS.get((fc, address + i)) for i in range(count)]
        if unit == 1 and None not in regs:
            body = bytes([unit, fc, 2 * count]) + b"".join(r.to_bytes(2) for r in regs)
        else:
            body = bytes([unit, fc | 0x80, 2])  # illegal data address
        crc = FramerRTU.compute_CRC(body)
        out += body + bytes([crc >> 8, crc & 0xFF])
    return out


# ---------------------------------------------------------------------------- the endpoint


def test_the_endpoint_of_a_device_servers_line_is_its_host_and_port() -> None:
    server = endpoint("modbus-rtu://10.0.0.2:4001?unit=3")
    assert (server.where, server.server, server.serial, server.device) == (
        "10.0.0.2:4001", ("10.0.0.2", 4001), True, False)  # fmt: skip
    device = endpoint("ascii:///dev/ttyUSB0")
    assert (device.where, device.server, device.serial, device.device) == (
        "/dev/ttyUSB0", None, True, True)  # fmt: skip
    tcp = endpoint("modbus-tcp://10.0.0.2")
    assert (tcp.where, tcp.server, tcp.serial, tcp.device) == ("10.0.0.2:502", None, False, False)


# ---------------------------------------------------------------------------- the drivers


def test_the_ascii_driver_reads_the_module_through_a_device_server() -> None:
    with tcp_server(ascii_module) as port:
        url = f"ascii://127.0.0.1:{port}?addr=01&checksum=0"
        with open_daq(url, timeout=2.0) as daq:
            assert isinstance(daq, AsciiDAQ) and daq.port == f"socket://127.0.0.1:{port}"
            assert (daq.identity.model, daq.identity.firmware) == ("LDQ412", "2.01")
            assert daq.scan_rate_hz == 20
            body = daq.transact(encode_command("#", 1, checksum=False))
            assert body == ASCII_ANSWERS[b"#01"]
            scan = daq.snapshot()
            assert (scan.counter, scan.codes) == (5, (0x800, 0x801, 0x7FF, 0x400))
            assert daq.url == f"ascii://127.0.0.1:{port}?baud=115200&addr=01&checksum=0"
            own_url = daq.url
        with open_daq(own_url, timeout=2.0) as again:  # the driver's own URL opens it again
            assert again.identity.model == "LDQ412"


def test_the_rtu_driver_reads_the_module_through_a_device_server() -> None:
    with tcp_server(rtu_module) as port:
        url = f"modbus-rtu://127.0.0.1:{port}?unit=1&fifo=0"
        with open_daq(url, timeout=2.0) as daq:
            assert (daq.identity.model, daq.identity.serial) == ("LDQ412", 0x00C0FFEE)
            scan = daq.snapshot()
            assert (scan.counter, scan.codes) == (5, (0x800, 0x801, 0x7FF, 0x400))
            assert daq.url == f"modbus-rtu://127.0.0.1:{port}?baud=115200&unit=1&fifo=0"
            own_url = daq.url
        with open_daq(own_url, timeout=2.0) as again:
            assert again.identity.firmware == "2.01"


@pytest.mark.slow
def test_the_probe_finds_the_module_behind_a_device_server() -> None:
    with tcp_server(ascii_module) as port:
        url = f"ascii://127.0.0.1:{port}?addr=01&checksum=0"
        found = probe(url, timeout=1.0, budget=10.0)
        assert found.found and found.answered_url == url, found
        assert found.module["scan"]["counter"] == 5
        elsewhere = probe(url.replace("addr=01", "addr=05"), timeout=1.0, budget=10.0)
    assert elsewhere.cause == "wrong_address" and elsewhere.answered_url == url, elsewhere
    assert elsewhere.message.startswith(f"address 05 does not answer at 127.0.0.1:{port}; ")


@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["ascii", "modbus-rtu"])
def test_the_probe_tries_no_other_rate_on_a_device_servers_line(scheme: str) -> None:
    with tcp_server("silent") as port:
        report = probe(f"{scheme}://127.0.0.1:{port}?baud=9600", timeout=0.2, budget=2.5)
    assert report.cause == "no_answer" and report.elapsed_s <= 2.5, report
    assert len(report.tried) >= 3  # the URL's, the datasheet's default, another
    assert {parse_url(a.url).params["baud"] for a in report.tried} == {"9600"}
    assert report.message.startswith(f"nothing answers at 127.0.0.1:{port} within 0.2 s (")
    assert "baud" not in report.message and "device server" in report.hint


def test_a_socket_lines_waiting_bytes_are_counted_whole() -> None:
    """pyserial's ``in_waiting`` of a socket line says 0 or 1, and pymodbus, which reads
    what waits and looks again a millisecond later, took a 245-byte FIFO answer a byte at a
    time: half a second, past a 0.25 s timeout (tests/drivers/test_stream.py's stall, on
    the emulator's device server). drivers/lines.py counts them as a tty does."""
    clock = ManualClock()
    with Emulator("modbus-rtu", clock=clock, line="tcp") as emu:
        clock.advance(2.0)  # 40 scans in the FIFO
        server = endpoint(emu.url).server
        assert server is not None
        request = FramerRTU(DecodePDU(False)).buildFrame(
            ReadInputRegistersRequest(address=ldq412.IR_FIFO, count=120, dev_id=1)
        )
        with serial.serial_for_url(f"socket://{server[0]}:{server[1]}", timeout=3) as line:
            line.write(request)
            deadline = time.monotonic() + 10
            while bytes_waiting(line) < 245 and time.monotonic() < deadline:
                time.sleep(0.01)
            assert bytes_waiting(line) == 245  # 20 scans of 6 registers, framed
            assert len(line.read(245)) == 245 and bytes_waiting(line) == 0
