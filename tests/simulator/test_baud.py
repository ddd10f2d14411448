"""The emulated serial line has a rate: a host at another rate than the module's is not
understood, and what the module sends reaches it as garbage (a UART at the wrong rate),
on real pseudo-terminals."""

from __future__ import annotations

import os
import time
from urllib.parse import urlsplit

import pytest
import serial
from hypothesis import given
from hypothesis import strategies as st

from loopcal.drivers import open_daq
from loopcal.drivers.errors import DAQTimeout
from loopcal.simulator.clock import ManualClock
from loopcal.simulator.emulator import Emulator
from loopcal.simulator.pty import tty_baud
from loopcal.simulator.wire import uart_receive
from tests.support.emulator import SILENCE_S
from tests.support.servers import running_link

RATES = [1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400]


@given(st.binary(max_size=64), st.sampled_from(RATES))
def test_the_same_rate_passes_every_byte(data: bytes, baud: int) -> None:
    assert uart_receive(data, baud, baud) == data


@given(st.binary(min_size=1, max_size=64), st.sampled_from(RATES), st.sampled_from(RATES))
def test_another_rate_reads_no_more_characters_than_start_bits(
    data: bytes, sent: int, heard: int
) -> None:
    """Each character a receiver reads starts at a falling edge of the line: never more of
    them than the sender's characters and data bits could make, and faster senders give
    the slower receiver fewer."""
    out = uart_receive(data, sent, heard)
    assert len(out) <= 5 * len(data)  # at most a falling edge per two bit times
    if heard * 10 <= sent:  # ten times slower: a character spans a sender's whole one
        assert len(out) <= len(data)


def test_a_slow_sender_reads_as_framing_errors_to_a_fast_receiver() -> None:
    # 9600 heard at 115200: a start bit lasts twelve receiver bits, the stop bit's sample
    # falls inside it, so the characters read are NUL (a framing error, as Linux delivers)
    assert set(uart_receive(b"#01\r", 9600, 115200)) == {0}
    # a fast sender heard by a slow receiver: few bytes, none of them the frame's
    assert uart_receive(b"$01M\r", 115200, 9600) not in (b"", b"$01M\r")


def test_bad_rates_are_refused() -> None:
    with pytest.raises(ValueError, match="> 0"):
        uart_receive(b"x", 0, 9600)


@pytest.mark.parametrize("transport", ["modbus-rtu", "ascii"])
def test_a_driver_at_the_module_rate_reads_it_and_at_another_gets_no_answer(transport: str):
    with Emulator(transport, clock=ManualClock(), baud=19200) as emu:
        assert "baud=19200" in emu.url
        with open_daq(emu.url, timeout=1.0) as daq:
            assert daq.identity.model == "LDQ412"
        for wrong in (115200, 9600):
            with pytest.raises(DAQTimeout):
                open_daq(emu.url.replace("baud=19200", f"baud={wrong}"), timeout=0.25)
        if transport == "ascii":
            # the garbage is in the module's line buffer until a CR ends it: an empty
            # frame, which gets no answer (what loopcal probe sends before each try)
            with serial.Serial(urlsplit(emu.url).path, 19200) as port:
                port.write(b"\r")
        with open_daq(emu.url, timeout=1.0) as daq:
            assert daq.identity.model == "LDQ412"


def _read_for(port: serial.Serial, seconds: float) -> bytes:
    got = b""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        got += port.read(256)
    return got


def test_each_side_keeps_its_rate_and_what_crosses_rates_is_garbled() -> None:
    with running_link(19200) as link:
        assert tty_baud(link.device_fd) == 19200
        with serial.Serial(link.host_path, 115200, timeout=SILENCE_S) as host:
            os.write(link.device_fd, b">0000123400ABCDEF800001FFFBB80004\r")
            garbled = _read_for(host, 0.3)
            assert garbled and garbled != b">0000123400ABCDEF800001FFFBB80004\r"
            host.baudrate = 19200  # the same rate: the same bytes
            os.write(link.device_fd, b"!01LDQ412\r")
            assert _read_for(host, 0.3) == b"!01LDQ412\r"
            assert tty_baud(host.fd) == 19200
