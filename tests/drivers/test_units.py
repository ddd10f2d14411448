"""Pure-logic tests of the drivers: URL dispatch, frame parsing, sequencing, the Scan record.

No transport is involved (and none is mocked): these functions take bytes / registers /
raw readings and return values or raise typed errors.
"""

from __future__ import annotations

import numpy as np
import pytest

from loopcal.drivers import ascii as asc
from loopcal.drivers import driver_for_url, ldq412, open_daq, parse_url
from loopcal.drivers.errors import DAQError, DAQInvalidCommand, DAQProtocolError, DAQTimeout
from loopcal.drivers.modbus import format_firmware, parse_fifo, parse_snapshot
from loopcal.drivers.records import Identity, Scan
from loopcal.drivers.registry import registered_schemes
from loopcal.drivers.sequence import RawSnapshot, Sequencer, derived_status, period_ticks_us
from loopcal.drivers.url import device_server, line_url, serial_options, socket_line

U32 = ldq412.U32_MOD
R = ldq412.STATUS_RESTART
O = ldq412.STATUS_OVERFLOW


# --------------------------------------------------------------------------- URLs


def test_schemes_registered() -> None:
    assert set(registered_schemes()) == {"modbus-tcp", "modbus-rtu", "ascii"}


@pytest.mark.parametrize(
    ("url", "host", "port", "path", "params"),
    [
        ("modbus-tcp://127.0.0.1:40123?unit=1", "127.0.0.1", 40123, "", {"unit": "1"}),
        ("modbus-tcp://plc.local", "plc.local", None, "plc.local", {}),  # path unused by TCP
        (
            "modbus-rtu:///dev/pts/7?baud=115200&unit=1",
            None,
            None,
            "/dev/pts/7",
            {"baud": "115200", "unit": "1"},
        ),
        (
            "ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=1",
            None,
            None,
            "/dev/ttyUSB0",
            {"baud": "115200", "addr": "01", "checksum": "1"},
        ),
        ("ascii://COM3?addr=0A", "com3", None, "COM3", {"addr": "0A"}),
        # a serial line behind a serial device server: a host and a TCP port, no path
        ("modbus-rtu://192.168.1.60:4001?unit=1", "192.168.1.60", 4001, "", {"unit": "1"}),
        ("ascii://[FE80::1]:4001/?addr=01", "fe80::1", 4001, "", {"addr": "01"}),
    ],
)
def test_parse_url(
    url: str, host: str | None, port: int | None, path: str, params: dict[str, str]
) -> None:
    u = parse_url(url)
    assert (u.host, u.port, u.path, dict(u.params)) == (host, port, path, params)


@pytest.mark.parametrize(
    "url",
    [
        "nope://x",  # unknown scheme
        "/dev/ttyUSB0",  # no scheme
        "modbus-tcp://127.0.0.1:1?unit=1&unit=2",  # repeated key
        "modbus-tcp://127.0.0.1:1?slave=1",  # unknown key (typo guard)
        "modbus-tcp://127.0.0.1:1?unit=x",  # not an int
        "modbus-tcp://127.0.0.1:99999",  # bad port
        "modbus-tcp://127.0.0.1:1?unit=300",  # unit out of range
        "modbus-rtu://?baud=9600",  # no port
        "modbus-rtu:///dev/x?parity=Q",
        "ascii:///dev/x?checksum=2",
        "ascii:///dev/x?addr=100",
        "ascii:///dev/x?addr=zz",
        "ascii://10.0.0.2:0",  # a device server's port 0
        "modbus-rtu://10.0.0.2:4001?baud=0",  # a device server's line: its settings checked
    ],
)
def test_bad_urls_raise_value_error_before_any_io(url: str) -> None:
    with pytest.raises(ValueError):
        open_daq(url)


@pytest.mark.parametrize(("url", "line"), [
    ("ascii://192.168.1.60:4001?addr=01&checksum=0", "socket://192.168.1.60:4001"),
    ("modbus-rtu://NPort.local:4002?unit=1&baud=9600", "socket://nport.local:4002"),
    ("modbus-rtu://[fe80::1]:4001", "socket://[fe80::1]:4001"),
    ("ascii:///dev/ttyUSB0", "/dev/ttyUSB0"),
    ("ascii://COM3", "COM3"),
])  # fmt: skip
def test_a_host_and_port_is_a_device_servers_line(url: str, line: str) -> None:
    cls, parsed = driver_for_url(url)
    options = cls.url_options(parsed)
    assert options["port"] == line
    server = device_server(line)
    assert server == ((parsed.host, parsed.port) if parsed.port else None)
    if server:
        assert socket_line(*server) == line
    # written as a URL again, the line is the same one
    again = parse_url(line_url(parsed.scheme, line))
    assert serial_options(again, "x")["port"] == line


def test_a_device_servers_line_keeps_its_serial_settings_checked() -> None:
    options = serial_options(parse_url("ascii://10.0.0.2:4001?baud=9600&parity=E&stopbits=2"), "")
    assert (options["baud"], options["parity"], options["stopbits"]) == (9600, "E", 2)
    for bad, words in [
        ("ascii://10.0.0.2:4001?baud=0", "baud=0 is outside"),
        ("modbus-rtu://10.0.0.2:4001?parity=Q", "parity='Q' is not one of"),
        ("ascii://10.0.0.2:0", "port 0 is not a TCP port"),
        ("modbus-rtu://?unit=1", "or modbus-rtu://HOST:PORT for a serial device server"),
    ]:
        with pytest.raises(ValueError, match=words):
            driver_for_url(bad)
    assert device_server("socket://h") is None and device_server("rfc2217://h:4001") is None
    assert line_url("ascii", "socket://[::1]:4001") == "ascii://[::1]:4001"


# --------------------------------------------------------------------------- ASCII frames


def test_encode_command_with_and_without_checksum() -> None:
    assert asc.encode_command("#", 1, checksum=False) == b"#01\r"
    # '#'=0x23 '0'=0x30 '1'=0x31 -> 0x84
    assert asc.encode_command("#", 1, checksum=True) == b"#0184\r"
    assert asc.encode_command("%", 0xA, "R00C8", checksum=False) == b"%0AR00C8\r"
    with pytest.raises(ValueError):
        asc.encode_command(">", 1, checksum=False)


def test_datasheet_example_scan() -> None:
    body = asc.unframe(b">0000123400ABCDEF800001FFFBB80004\r", checksum=False)
    snap = asc.parse_scan(body, 1)
    assert snap == RawSnapshot(0x1234, 0x00ABCDEF, (2048, 1, 4095, 3000), 0x0004)


def test_checksum_verified() -> None:
    body = b">0000123400ABCDEF800001FFFBB80004"
    good = body + ldq412.ascii_checksum(body) + b"\r"
    assert asc.unframe(good, checksum=True) == body
    bad = body + b"00\r"
    with pytest.raises(DAQProtocolError, match="checksum"):
        asc.unframe(bad, checksum=True)
    lower = body + ldq412.ascii_checksum(body).lower() + b"\r"
    if lower != good:
        with pytest.raises(DAQProtocolError):
            asc.unframe(lower, checksum=True)


@pytest.mark.parametrize(
    "line",
    [
        b">0000123400ABCDEF800001FFFBB80004",  # no CR: partial
        b"\r",  # empty
        b"\x00\xff>0000123400ABCDEF800001FFFBB80004\r",  # garbage before
    ],
)
def test_unframe_rejects(line: bytes) -> None:
    with pytest.raises(DAQProtocolError):
        asc.unframe(line, checksum=False)


@pytest.mark.parametrize(
    "body",
    [
        b">0000123400ABCDEF800001FFFBB8000",  # one digit short
        b">0000123400ABCDEF800001FFFBB800040",  # one digit long
        b">0000123400ABCDEF800001FFFBB8000G",  # non-hex
        b">0000123400ABCDEF800001FFFBB8 004",  # space
        b">+000123400ABCDEF800001FFFBB80004",  # sign int() would accept
        b">0_00123400ABCDEF800001FFFBB80004",  # underscore int() would accept
        b"!0000123400ABCDEF800001FFFBB80004",  # wrong lead
        b"xyz>0000123400ABCDEF800001FFFBB80004",  # junk before a valid answer
    ],
)
def test_parse_scan_strict(body: bytes) -> None:
    with pytest.raises(DAQProtocolError):
        asc.parse_scan(body, 1)


def test_parse_scan_accepts_lowercase_data_digits() -> None:
    assert asc.parse_scan(b">0000123400abcdef800001fffbb80004", 1).time_us == 0xABCDEF


def test_rejection_and_acks() -> None:
    with pytest.raises(DAQInvalidCommand):
        asc.parse_scan(b"?01", 1)
    with pytest.raises(DAQProtocolError):
        asc.parse_ack(b"?02", 1)  # foreign address
    assert asc.parse_ack(b"!01LDQ412", 1) == b"LDQ412"
    assert asc.parse_ack(b"!1F", 0x1F) == b""
    with pytest.raises(DAQProtocolError):
        asc.parse_ack(b"!02LDQ412", 1)
    assert asc.parse_firmware(b"2.01") == "2.01"
    assert asc.parse_firmware(b"12.34") == "12.34"
    for bad in (b"2.1", b"2,01", b"v2.01", b"2.01 "):
        with pytest.raises(DAQProtocolError):
            asc.parse_firmware(bad)
    assert asc.parse_rate(b"00C8") == 200
    for bad in (b"0000", b"00C9", b"C8", b"00c8x"):
        with pytest.raises(DAQProtocolError):
            asc.parse_rate(bad)
    assert asc.parse_channel(b">FFF", 1) == 4095
    with pytest.raises(DAQProtocolError):
        asc.parse_channel(b">FFFF", 1)


# --------------------------------------------------------------------------- Modbus registers


def test_parse_snapshot() -> None:
    regs = [0x0001, 0x0002, 0x00AB, 0xCDEF, 1, 2, 3, 4095, R | 0x8, 17]
    s = parse_snapshot(regs)
    assert s == RawSnapshot(0x10002, 0xABCDEF, (1, 2, 3, 4095), R | 0x8, 17)
    with pytest.raises(DAQProtocolError):
        parse_snapshot(regs[:9])
    with pytest.raises(DAQProtocolError):
        parse_snapshot([*regs[:4], 4096, *regs[5:]])
    with pytest.raises(DAQProtocolError):
        parse_snapshot([*regs[:9], 257])


def test_parse_fifo_drops_filler_and_rejects_partial_filler() -> None:
    f = [0xFFFF] * 6
    regs = [0, 5, 1, 2, 3, 4, 0xFFFF, 0xFFFF, 4095, 0, 7, 8, *f, *f]
    assert parse_fifo(regs) == ([(5, (1, 2, 3, 4)), (0xFFFFFFFF, (4095, 0, 7, 8))], 2)
    with pytest.raises(DAQProtocolError):
        parse_fifo([0, 5, 1, 2, 3, 0xFFFF])
    with pytest.raises(DAQProtocolError):
        parse_fifo(regs[:7])
    with pytest.raises(DAQProtocolError):  # a scan after filler: not a FIFO answer
        parse_fifo([*f, 0, 5, 1, 2, 3, 4])


def test_format_firmware() -> None:
    assert format_firmware(0x0201) == "2.01"
    assert format_firmware(0x0A0F) == "10.15"
    assert Identity("LDQ412", "2.01", 1).firmware_version == (2, 1)


# --------------------------------------------------------------------------- sequencing


def snap(
    counter: int,
    rate: int = 20,
    status: int = 0,
    t0: int = 0,
    level: int = 0,
    codes: tuple[int, int, int, int] = (1, 2, 3, 4),
) -> RawSnapshot:
    t = (t0 + period_ticks_us(counter, rate)) % U32
    return RawSnapshot(counter % U32, t, codes, status, level)


def test_period_ticks_rounding() -> None:
    assert period_ticks_us(1, 20) == 50_000
    assert period_ticks_us(-3, 200) == -15_000
    assert period_ticks_us(1, 3) == 333_333
    assert period_ticks_us(2, 3) == 666_667
    assert period_ticks_us(-2, 3) == -666_667


def test_poll_dedupe_gaps_and_first_restart_flag() -> None:
    seq = Sequencer(20)
    s, new = seq.poll(snap(10, status=R), 0.0)
    assert new and s.restarted and s.missed == 0 and s.counter64 == 10
    s, new = seq.poll(snap(10, status=R), 0.0)
    assert not new and not s.restarted
    s, new = seq.poll(snap(14, status=R), 0.0)  # bit still set: not a new restart
    assert new and s.missed == 3 and not s.restarted
    assert s.time64_us == 14 * 50_000 and s.time_measured


def test_poll_counter_and_time_wrap() -> None:
    seq = Sequencer(200)
    c0 = U32 - 2
    t0 = U32 - 6000
    seq.poll(RawSnapshot(c0, t0, (0, 0, 0, 0), 0), 0.0)
    s, new = seq.poll(RawSnapshot(3, (t0 + 5 * 5000) % U32, (0, 0, 0, 0), 0), 0.0)
    assert new and not s.restarted
    assert s.counter64 == c0 + 5 and s.missed == 4
    assert s.counter == 3
    assert (
        s.time64_us - seq.peek(RawSnapshot(3, (t0 + 25000) % U32, (0,) * 4, 0), 0.0).time64_us == 0
    )


def test_first_anchor_estimates_time_wraps() -> None:
    seq = Sequencer(20)
    counter = 90_000  # 75 min at 20 Hz: device time wrapped once
    true_t = counter * 50_000
    s, _ = seq.poll(RawSnapshot(counter, true_t % U32, (0,) * 4, 0), 0.0)
    assert s.time64_us == true_t


def test_poll_restart_by_counter_regression_and_by_bit_edge() -> None:
    seq = Sequencer(20)
    seq.poll(snap(1000), 0.0)
    s, new = seq.poll(snap(5), 0.0)  # counter back: restart even without the bit
    assert new and s.restarted and s.epoch == 1 and s.missed == 5 and s.counter64 == 5
    seq.poll(snap(6), 0.0)
    s, new = seq.poll(snap(2000, status=R), 0.0)  # bit rises while counter went up
    assert new and s.restarted and s.epoch == 2 and s.counter64 == 2000
    assert seq.restarts_detected == 2


def made(host: float, on: float, rate: int = 50, slow: float = 0.0) -> RawSnapshot:
    """The snapshot a module powered on at host time ``on`` s holds at host time ``host``
    s (its restart bit set, as over ASCII); its clock ``slow`` (relative) slow."""
    counter = int((host - on) * (1 - slow) * rate)
    return RawSnapshot(counter, 1809 + period_ticks_us(counter, rate), (1, 2, 3, 4), R)


def test_a_restart_the_counter_hides_is_told_by_the_hosts_clock() -> None:
    # ci65: the module ran 1.2 s, was off while polls failed, and the first answer after
    # it showed a counter past the last one (its restart bit set all along, over ASCII)
    seq = Sequencer(50)
    seq.poll(made(11.2, on=10.0), 11.201, sent=11.199)
    s, new = seq.poll(made(31.0, on=15.5), 31.003, sent=31.0)  # off 4 s: 4.3 s behind
    assert new and s.restarted and s.epoch == 1 and s.counter64 == s.missed == 775
    s, new = seq.poll(made(31.1, on=15.5), 31.103, sent=31.1)
    assert new and not s.restarted and s.epoch == 1 and s.missed == 4


@pytest.mark.parametrize(
    ("case", "answer_at", "sent", "arrived"),
    [
        ("an answer held 2.9 s on the way", 17.1, 20.0, 20.002),
        ("a host stopped 10 s while it waited", 20.003, 20.0, 30.0),
    ],
)
def test_a_late_answer_is_not_taken_for_a_restart(case, answer_at, sent, arrived) -> None:
    seq = Sequencer(50)
    seq.poll(made(11.2, on=10.0), 11.201, sent=11.199)
    s, new = seq.poll(made(answer_at, on=10.0), arrived, sent=sent)
    assert new and not s.restarted and s.epoch == 0, case
    s, _ = seq.poll(made(30.05, on=10.0), 30.052, sent=30.05)  # a prompt answer after it
    assert not s.restarted and s.epoch == 0, case


def test_the_hosts_clock_allows_for_drift_a_rate_change_and_a_short_power_cycle() -> None:
    seq = Sequencer(50)
    for h in np.arange(11.0, 111.0, 1.0):  # a clock 0.4 % slow, then polls fail 10 min
        seq.poll(made(h, on=10.0, slow=0.004), h + 0.002, sent=h)
    s, _ = seq.poll(made(711.0, on=10.0, slow=0.004), 711.002, sent=711.0)
    assert not s.restarted and s.epoch == 0
    seq = Sequencer(50)  # somebody set the rate to 25 Hz: half the scans, the time runs on
    seq.poll(made(11.0, on=10.0), 11.002, sent=11.0)
    late = made(31.0, on=10.0)
    half = RawSnapshot(50 + 500, late.time_us, late.codes, R)
    s, _ = seq.poll(half, 31.002, sent=31.0)
    assert not s.restarted and s.epoch == 0
    seq = Sequencer(50)  # on 1.2 s, off 1 s: within the allowance, not told (ASCII docs)
    seq.poll(made(11.2, on=10.0), 11.202, sent=11.2)
    s, _ = seq.poll(made(31.0, on=12.5), 31.002, sent=31.0)
    assert not s.restarted and s.epoch == 0


def fifo_raw(c0: int, n: int) -> list[tuple[int, tuple[int, int, int, int]]]:
    return [((c0 + i) % U32, (i % 4096, 1, 2, 3)) for i in range(n)]


def test_fifo_times_are_derived_from_the_anchor_and_the_anchor_scan_is_measured() -> None:
    seq = Sequencer(20)
    seq.begin_batch(
        snap(
            109, t0=777, level=10, status=ldq412.STATUS_FAULT_MASK & 0x20, codes=(9, 4095, 4095, 3)
        )
    )
    raw = fifo_raw(100, 10)
    raw[5] = (105, (0, 4095, 4095, 7))
    raw[-1] = (109, (9, 4095, 4095, 3))
    out = seq.fifo_scans(raw, 1.0)
    assert [s.counter for s in out] == list(range(100, 110))
    assert [s.time_us for s in out] == [777 + c * 50_000 for c in range(100, 110)]
    assert [s.time_measured for s in out] == [False] * 9 + [True]
    assert out[-1].status == 0x20 and out[-1].status_measured
    # derived: rail from codes (ch1 at 0, ch2 and ch3 at 4095), fault only where the
    # anchor says so (ch2) and the code is 4095
    assert out[5].status == 0b0111 | 0x20
    assert out[0].missed == 0 and all(s.missed == 0 for s in out)


def test_fifo_gap_overflow_duplicates_and_wrap() -> None:
    seq = Sequencer(200)
    c0 = U32 - 5
    seq.begin_batch(snap(c0 + 3, rate=200))
    a = seq.fifo_scans(fifo_raw(c0, 4), 0.0)
    assert [s.counter64 for s in a] == [c0, c0 + 1, c0 + 2, c0 + 3]
    seq.begin_batch(snap(c0 + 30, rate=200, status=O))
    b = seq.fifo_scans(fifo_raw(c0 + 2, 2) + fifo_raw(c0 + 10, 21), 0.0)
    # the two re-delivered scans are dropped; the gap of 6 is reported once, with overflow
    assert [s.counter64 for s in b] == list(range(c0 + 10, c0 + 31))
    assert b[0].missed == 6 and b[0].overflow and not b[1].overflow
    assert b[-1].counter == (c0 + 30) % U32 and b[-1].time64_us == period_ticks_us(c0 + 30, 200)


def test_fifo_restart_boundary() -> None:
    seq = Sequencer(20)
    seq.begin_batch(snap(50))
    seq.fifo_scans(fifo_raw(41, 10), 0.0)
    # power cycle: FIFO restarted at 0, restart bit set
    seq.begin_batch(snap(7, status=R))
    out = seq.fifo_scans(fifo_raw(2, 6), 0.0)
    assert out[0].restarted and out[0].epoch == 1 and out[0].missed == 2
    assert [s.counter64 for s in out] == [2, 3, 4, 5, 6, 7]
    assert not any(s.restarted for s in out[1:])
    # a device whose FIFO kept old scans across the cycle: boundary at the regression
    seq.begin_batch(snap(3, status=R))
    out = seq.fifo_scans([(8, (0, 0, 0, 0)), (9, (0, 0, 0, 0)), (0, (0, 0, 0, 0))], 0.0)
    # no bit edge (never cleared) but the snapshot counter went back: a restart, placed at
    # the FIFO scan where the counter goes back
    assert [(s.epoch, s.counter64, s.restarted) for s in out] == [
        (1, 8, False),
        (1, 9, False),
        (2, 0, True),
    ]


def test_fifo_restart_boundary_at_regression() -> None:
    seq = Sequencer(20)
    seq.begin_batch(snap(10))
    seq.fifo_scans(fifo_raw(5, 6), 0.0)
    seq.begin_batch(snap(1, status=R, t0=0))
    seq.restart_bit_cleared()
    out = seq.fifo_scans([(11, (0,) * 4), (12, (0,) * 4), (0, (0,) * 4), (1, (0,) * 4)], 0.0)
    assert [(s.epoch, s.counter64) for s in out] == [(0, 11), (0, 12), (1, 0), (1, 1)]
    assert [s.restarted for s in out] == [False, False, True, False]
    # a later bit edge is a new restart
    seq.begin_batch(snap(400, status=R))
    out = seq.fifo_scans(fifo_raw(395, 6), 0.0)
    assert out[0].restarted and out[0].epoch == 2 and out[0].missed == 395


def test_restart_seen_on_empty_batch_is_reported_on_the_next_scan() -> None:
    seq = Sequencer(20)
    seq.begin_batch(snap(10))
    seq.fifo_scans(fifo_raw(8, 3), 0.0)
    seq.begin_batch(snap(0, status=R))
    assert seq.fifo_scans([], 0.0) == []
    seq.restart_bit_cleared()
    seq.begin_batch(snap(3))
    out = seq.fifo_scans(fifo_raw(0, 4), 0.0)
    assert out[0].restarted and out[0].missed == 0 and out[0].epoch == 1


def test_peek_does_not_change_state() -> None:
    seq = Sequencer(20)
    seq.poll(snap(10), 0.0)
    p = seq.peek(snap(15), 0.0)
    assert p.missed == 4
    s, _ = seq.poll(snap(12), 0.0)
    assert s.missed == 1


def test_rate_mismatch_detection() -> None:
    seq = Sequencer(20)
    seq.poll(snap(0, rate=10), 0.0)
    seq.poll(snap(40, rate=10), 0.0)
    assert seq.period_mismatch()
    seq.set_rate(10)
    assert not seq.period_mismatch()


def test_derived_status() -> None:
    assert derived_status((0, 1, 4095, 5), 0x00F0 | R) == 0b0101 | 0x40 | R


def test_scan_properties() -> None:
    s = Scan(
        counter=1,
        time_us=2,
        codes=(0, 2048, 4095, 1),
        status=0b0101 | 0x40 | R | O,
        counter64=1,
        time64_us=2_000_000,
    )
    assert s.rail == (True, False, True, False)
    assert s.fault == (False, False, True, False)
    assert s.trustworthy == (False, True, False, True)
    assert s.restart_latched and s.overflow_latched
    assert s.time_s == 2.0
    np.testing.assert_allclose(s.volts, ldq412.code_to_volts(np.array([0, 2048, 4095, 1])))


def test_error_hierarchy() -> None:
    assert issubclass(DAQTimeout, TimeoutError) and issubclass(DAQTimeout, DAQError)
    assert issubclass(DAQInvalidCommand, DAQProtocolError)
