"""The ASCII protocol: pure frame handling, then over a real pty with raw pyserial."""

from __future__ import annotations

import time
from urllib.parse import parse_qs, urlsplit

import pytest
import serial

from loopcal.simulator.ascii_protocol import handle_frame
from loopcal.simulator.clock import ManualClock
from loopcal.simulator.device import LDQ412
from loopcal.simulator.emulator import Emulator
from tests.support.emulator import ANSWER_S, SILENCE_S, ascii_ask, golden_source

GOLDEN_BODY = b">0000123400ABCDEF800001FFFBB80004"


def port_of(url: str) -> str:
    return urlsplit(url).path


def open_port(url: str) -> serial.Serial:
    return serial.Serial(port_of(url), 115200, timeout=ANSWER_S)


# ---------------------------------------------------------------- pure frame handling


@pytest.fixture
def dev() -> LDQ412:
    return LDQ412(golden_source(), scan_rate_hz=20, firmware=(2, 1))


@pytest.mark.parametrize(
    ("frame", "answer"),
    [
        (b"#012", b">001\r"),
        (b"#013", b">FFF\r"),
        (b"#014", b">BB8\r"),
        (b"$01M", b"!01LDQ412\r"),
        (b"$01F", b"!012.01\r"),
        (b"$01R", b"!010014\r"),
        (b"#010", b"?01\r"),  # channel 0 does not exist
        (b"#015", b"?01\r"),
        (b"#0112", b"?01\r"),
        (b"$01", b"?01\r"),
        (b"$01m", b"?01\r"),
        (b"$01MX", b"?01\r"),
        (b"%01R", b"?01\r"),
        (b"%01R00C9", b"?01\r"),  # 201 Hz: out of range
        (b"%01R0000", b"?01\r"),
        (b"%01R12G4", b"?01\r"),
        (b"%01R00640", b"?01\r"),
        (b"@01", b"?01\r"),  # addressed to us, not a command of ours
        (b"#02", None),  # another module
        (b"#0", None),
        (b"#1", None),
        (b"", None),
        (b">01", None),  # another module's answer on a shared line
        (b"!01", None),
        (b"?01", None),
        (b"#01\x00", None),  # not printable: line noise
    ],
)
def test_frames_without_checksum(dev, frame, answer):
    assert handle_frame(dev, frame, 0x01) == answer


def test_set_scan_rate_takes_both_hex_cases_and_applies(dev):
    assert handle_frame(dev, b"%01R00c8", 1) == b"!01\r"
    assert dev.scan_rate_hz == 200
    assert handle_frame(dev, b"%01R0001", 1) == b"!01\r"
    assert handle_frame(dev, b"$01R", 1) == b"!010001\r"
    assert handle_frame(dev, b"%01R00C9", 1) == b"?01\r"
    assert dev.scan_rate_hz == 1


def test_checksum_mode_on_commands_and_answers(dev):
    dev.write_registers(4, [1])
    assert handle_frame(dev, b"$01MD2", 1) == b"!01LDQ412FA\r"
    assert handle_frame(dev, b"#013B7", 1) == b">FFF10\r"
    assert handle_frame(dev, b"%01R0064A2", 1) == b"!0182\r"
    assert handle_frame(dev, b"$01RD7", 1) == b"!0100644C\r"
    assert handle_frame(dev, b"$01XDD", 1) == b"?01A0\r"  # valid checksum, invalid command
    assert handle_frame(dev, b"$01MD3", 1) is None  # wrong checksum
    assert handle_frame(dev, b"$01Md2", 1) is None  # checksum digits must be uppercase
    assert handle_frame(dev, b"$01M", 1) is None  # checksum missing
    assert handle_frame(dev, b"$02MD3", 1) is None  # right checksum, other module
    assert handle_frame(dev, b"D", 1) is None


def test_other_address_and_lowercase_address():
    dev = LDQ412(golden_source())
    assert handle_frame(dev, b"$1FM", 0x1F) == b"!1FLDQ412\r"
    assert handle_frame(dev, b"$1fM", 0x1F) is None
    assert handle_frame(dev, b"$01M", 0x1F) is None


# ---------------------------------------------------------------- over a real pty


def drive_to_golden_state(emu: Emulator, clock: ManualClock, port: serial.Serial) -> None:
    """Counter 0x1234 at device time 0x00ABCDEF, restart and overflow flags cleared.

    At 2 Hz, scan 708 happens at 354.0 s; a switch to 1 Hz at 354.226671 s puts scan
    708 + 3952 = 4660 = 0x1234 at 4306.226671 s = 2**32 us + 0xABCDEF us.
    """
    clock.advance(354.226671)
    assert ascii_ask(port, b"%01R0001\r") == b"!01\r"
    clock.advance(3951.5)  # scan 4659 at 4305.226671 s
    with emu.handle.synced() as device:
        device.write_registers(2, [1, 1])  # clear FIFO + overflow, clear restart
    clock.advance(0.5)


def test_golden_latest_scan_with_and_without_checksum():
    clock = ManualClock()
    with Emulator("ascii", golden_source(), scan_rate_hz=2, clock=clock) as emu:
        with open_port(emu.url) as port:
            drive_to_golden_state(emu, clock, port)
            assert ascii_ask(port, b"#01\r") == b">0000123400ABCDEF800001FFFBB80004\r"
            truth = emu.truth[-1]
            assert (truth.counter, truth.time_us, truth.codes) == (
                0x1234,
                0x00ABCDEF,
                (2048, 1, 4095, 3000),
            )
            with emu.handle.synced() as device:
                device.write_registers(4, [1])  # checksum mode is shared with Modbus
            assert ascii_ask(port, b"#0184\r") == GOLDEN_BODY + b"38\r"
            assert ascii_ask(port, b"#01\r", SILENCE_S) == b""  # no checksum: no answer


def test_all_commands_over_the_wire_and_silence():
    clock = ManualClock()
    with Emulator("ascii", golden_source(), clock=clock, firmware=(3, 7)) as emu:
        query = parse_qs(urlsplit(emu.url).query)
        assert query == {"baud": ["115200"], "addr": ["01"], "checksum": ["0"]}
        assert port_of(emu.url).startswith("/dev/pts/")
        with open_port(emu.url) as port:
            clock.advance(0.5)
            answer = ascii_ask(port, b"#01\r")
            assert answer == b">0000000A0007A120800001FFFBB80204\r"  # restart bit set
            assert ascii_ask(port, b"#011\r") == b">800\r"
            assert ascii_ask(port, b"$01M\r") == b"!01LDQ412\r"
            assert ascii_ask(port, b"$01F\r") == b"!013.07\r"
            assert ascii_ask(port, b"$01R\r") == b"!010014\r"
            assert ascii_ask(port, b"%01R00C8\r") == b"!01\r"
            assert ascii_ask(port, b"$01R\r") == b"!0100C8\r"
            assert ascii_ask(port, b"$01Q\r") == b"?01\r"
            started = time.monotonic()
            assert ascii_ask(port, b"#02\r", SILENCE_S) == b""
            assert time.monotonic() - started >= SILENCE_S * 0.9
            # two frames in one write are both answered, in order
            port.write(b"$01R\r#014\r")
            assert port.read_until(b"\r") == b"!0100C8\r"
            assert port.read_until(b"\r") == b">BB8\r"


def test_checksum_from_power_on_and_custom_address():
    with Emulator(
        "ascii", golden_source(), clock=ManualClock(), ascii_addr=0x2A, ascii_checksum=True
    ) as emu:
        assert "addr=2A" in emu.url and "checksum=1" in emu.url
        with open_port(emu.url) as port:
            assert ascii_ask(port, b"$2AM" + b"%02X" % (sum(b"$2AM") & 0xFF) + b"\r") == (
                b"!2ALDQ412" + b"%02X" % (sum(b"!2ALDQ412") & 0xFF) + b"\r"
            )
            assert ascii_ask(port, b"$2AM\r", SILENCE_S) == b""
