"""The three drivers against the emulated LDQ-412 over real transports.

Modbus TCP on 127.0.0.1, Modbus RTU and ASCII behind the emulated serial device server
(loopback TCP: tests.support.drivers.tcp_line says why not a pseudo-terminal). Mostly on a
ManualClock, so each scenario is deterministic and as fast as the wire allows: the test
decides exactly how much device time passes between two driver calls. Every scan a
driver delivers is compared with the emulator's ground truth (Emulator.truth).
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from loopcal.drivers import DAQ, Scan, ldq412, open_daq
from loopcal.drivers.errors import (
    DAQDisconnected,
    DAQModbusException,
    DAQProtocolError,
    DAQTimeout,
)
from loopcal.drivers.modbus import ModbusDAQ
from loopcal.simulator.clock import ManualClock, SimClock
from loopcal.simulator.emulator import Emulator
from tests.support.drivers import (
    BOUND_S,
    OK_TIMEOUT,
    PERIOD,
    RATE,
    TIMEOUT,
    TRANSPORTS,
    assert_fifo_delivered,
    assert_gaps_explained,
    check_against_truth,
    read_ok,
    timed_reads,
    worst_call_s,
)

MODBUS = ["modbus-tcp", "modbus-rtu"]


def advance_and_read(daq: DAQ, clock: ManualClock, scans: int) -> list[Scan]:
    """``scans`` scan periods of device time, then a read (retried through a timeout, as
    the daemon does: the emulator shares this process, and at the fault tests' 0.25 s a
    loaded machine made a read before the fault time out). A read that is a test's
    subject calls ``daq.read_scans()`` itself."""
    clock.advance(scans * PERIOD)
    return read_ok(daq)


# --------------------------------------------------------------------------- ground truth


@pytest.mark.slow
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_2000_consecutive_scans_equal_truth(emu_factory, transport: str) -> None:
    emu, daq, clock = emu_factory(transport)
    rng = np.random.default_rng(1)
    got: list[Scan] = []
    while len(got) < 2000:
        # FIFO: anything from 0 to 60 scans per call; ASCII polls once per scan period
        n = 1 if transport == "ascii" else int(rng.integers(0, 61))
        got += advance_and_read(daq, clock, n)
    check_against_truth(got, emu)
    if transport == "ascii":  # one poll a scan: a poll retried still finds its scan
        truth = emu.truth
        first = got[0].counter
        assert [s.counter for s in got] == [t.counter for t in truth[first : first + len(got)]]
        assert all(s.missed == 0 for s in got)
    else:
        assert_fifo_delivered(got, emu, daq)
    assert all(s.time64_us == s.counter64 * 1_000_000 // RATE for s in got)
    # FIFO scans carry derived time; the one equal to the snapshot's is measured
    if transport != "ascii":
        assert any(s.time_measured for s in got) and not all(s.time_measured for s in got)


@pytest.mark.slow
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_real_time_sim_clock(emu_factory, transport: str) -> None:
    """Free-running clock (5x real time, 1000 device scans/s), scans arriving while the
    driver reads: every scan delivered is the module's, every gap is counted. The FIFO
    drivers miss a scan only in an overflow, and only after the host left the FIFO unread
    longer than it holds (256 ms here: a busy machine may), or with a read the driver gave
    up on (an answer a busy machine held past the timeout: a machine-wide stall of 0.8 s
    was seen, and the emulator shares this process); ASCII polling misses some. How many
    scans a second each driver sustains is bench/bench_drivers.py's figure."""
    speed = 5.0
    emu, daq, _ = emu_factory(transport, clock=SimClock(speed))
    pause = 0.001 if transport == "ascii" else 0.01
    calls = timed_reads(daq, until=time.monotonic() + 2.0, min_calls=50, pause_s=pause)
    got = [s for c in calls for s in c.scans]
    check_against_truth(got, emu)
    span = got[-1].counter64 - got[0].counter64 + 1
    assert len(got) + sum(s.missed for s in got[1:]) == span
    if transport != "ascii":
        assert_gaps_explained(calls, fifo_s=ldq412.FIFO_DEPTH / (RATE * speed))


# --------------------------------------------------------------------------- identity


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_identity(emu_factory, transport: str) -> None:
    emu, daq, _ = emu_factory(transport, serial_number=0x12345678, firmware=(3, 7))
    assert daq.identity.model == ldq412.MODEL_NAME
    assert daq.identity.firmware == "3.07"
    assert daq.identity.serial == (None if transport == "ascii" else 0x12345678)


@pytest.mark.slow
def test_wrong_unit_or_address_times_out_at_open() -> None:
    with Emulator("modbus-tcp", clock=ManualClock(), unit=5) as emu:
        t0 = time.monotonic()
        with pytest.raises(DAQTimeout):
            open_daq(emu.url.replace("unit=5", "unit=1"), timeout=TIMEOUT)
        assert time.monotonic() - t0 < BOUND_S
    with Emulator("ascii", clock=ManualClock(), ascii_addr=0x22) as emu:
        with pytest.raises(DAQTimeout):
            open_daq(emu.url.replace("addr=22", "addr=01"), timeout=TIMEOUT)


def test_nothing_there() -> None:
    t0 = time.monotonic()
    with pytest.raises(DAQDisconnected):
        open_daq("modbus-tcp://127.0.0.1:1?unit=1", timeout=TIMEOUT)
    with pytest.raises(DAQDisconnected):
        open_daq("modbus-rtu:///dev/does-not-exist?unit=1")
    with pytest.raises(DAQDisconnected):
        open_daq("ascii:///dev/does-not-exist")
    assert time.monotonic() - t0 < BOUND_S


# --------------------------------------------------------------------------- wire faults


@pytest.mark.slow
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_stall_times_out_within_bound_then_recovers(emu_factory, transport: str) -> None:
    emu, daq, clock = emu_factory(transport, TIMEOUT)
    got = advance_and_read(daq, clock, 10)
    emu.faults.stall(1.0)  # device seconds: the ManualClock is not moving
    for _ in range(3):
        t0 = time.monotonic()
        with pytest.raises(DAQTimeout):
            daq.read_scans()
        assert time.monotonic() - t0 < BOUND_S
    clock.advance(1.0)
    got += read_ok(daq)
    got += advance_and_read(daq, clock, 5)
    check_against_truth(got, emu)
    if transport != "ascii":  # the FIFO kept every scan through the stall
        assert_fifo_delivered(got, emu, daq)


@pytest.mark.slow
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_disconnect_then_reconnect(emu_factory, transport: str) -> None:
    emu, daq, clock = emu_factory(transport, TIMEOUT)
    got = advance_and_read(daq, clock, 10)
    emu.faults.disconnect()
    clock.advance(20 * PERIOD)
    expected = DAQDisconnected if transport == "modbus-tcp" else DAQTimeout
    for _ in range(2):
        t0 = time.monotonic()
        with pytest.raises(expected):
            daq.read_scans()
        assert time.monotonic() - t0 < BOUND_S
    emu.faults.reconnect()
    got += read_ok(daq)
    got += advance_and_read(daq, clock, 5)
    check_against_truth(got, emu)
    if transport != "ascii":
        assert_fifo_delivered(got, emu, daq)
    else:
        assert got[-2].missed == 19  # 20 scans passed between the two polls


@pytest.mark.slow
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_corrupt_answer_is_a_protocol_error_then_recovers(emu_factory, transport: str) -> None:
    # the module answers (corrupt or not): no timeout is provoked, and a short one was
    # reached under load in a whole run on four workers
    emu, daq, clock = emu_factory(transport, OK_TIMEOUT)
    got = advance_and_read(daq, clock, 10)
    for _ in range(3):
        emu.faults.corrupt_next(1)
        clock.advance(7 * PERIOD)
        t0 = time.monotonic()
        with pytest.raises(DAQProtocolError):
            daq.read_scans()
        assert time.monotonic() - t0 < worst_call_s(daq.timeout)
        # recovered: the next reads deliver every scan (ci65: the pty held the next answer
        # past 3 s under load, a timeout read_ok reads through as the daemon does)
        got += read_ok(daq)
    check_against_truth(got, emu)
    if transport != "ascii":  # the corrupted answer was the snapshot: no scan lost
        assert_fifo_delivered(got, emu, daq)


@pytest.mark.slow
@pytest.mark.parametrize("transport", MODBUS)
def test_corrupt_fifo_answer_reports_the_lost_scans(emu_factory, transport: str) -> None:
    # the module answers (corrupt): no timeout is its subject, and under two CPU hogs the
    # corrupt answer came after 0.25 s (a timeout, not the protocol error)
    emu, daq, clock = emu_factory(transport, OK_TIMEOUT)
    assert isinstance(daq, ModbusDAQ)
    got = advance_and_read(daq, clock, 10)
    clock.advance(10 * PERIOD)
    emu.faults.corrupt_next(1)
    with pytest.raises(DAQProtocolError):
        daq.read_input_registers(ldq412.IR_FIFO, 3 * ldq412.FIFO_SCAN_REGS)  # pops 3
    got += daq.read_scans()
    check_against_truth(got, emu)
    assert got[-7].missed == 3 and sum(s.missed for s in got) == 3


@pytest.mark.slow
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_garbage_before_an_answer(emu_factory, transport: str) -> None:
    # the module answers (after junk): no timeout is its subject, and under two CPU hogs an
    # ASCII answer came after the fault tests' 0.25 s (a timeout, neither outcome)
    emu, daq, clock = emu_factory(transport, OK_TIMEOUT)
    got = advance_and_read(daq, clock, 10)
    outcomes = []
    for n in (1, 5, 17, 64):
        emu.faults.garbage(n)
        clock.advance(3 * PERIOD)
        t0 = time.monotonic()
        try:
            got += daq.read_scans()  # the framer may resync on a valid CRC after the junk
            outcomes.append("ok")
        except DAQProtocolError:
            outcomes.append("protocol error")
        assert time.monotonic() - t0 < worst_call_s(daq.timeout)
        got += advance_and_read(daq, clock, 1)
    check_against_truth(got, emu)
    assert "protocol error" in outcomes
    if transport != "ascii":
        assert_fifo_delivered(got, emu, daq)


@pytest.mark.slow
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_restart_is_reported_and_cleared(emu_factory, transport: str) -> None:
    emu, daq, clock = emu_factory(transport, TIMEOUT)
    got = advance_and_read(daq, clock, 300 if transport != "ascii" else 1)
    for _ in range(30):  # ASCII: counter well above what it will be after the restart
        got += advance_and_read(daq, clock, 5)
    assert got[0].restarted  # restart bit set at connect (power-on)
    assert not any(s.restarted for s in got[1:])
    emu.faults.restart()
    clock.advance(1.0)
    with pytest.raises((DAQTimeout, DAQDisconnected)):  # module off: silent
        daq.read_scans()
    clock.advance(1.0 + 10 * PERIOD)  # back on, 10 scans made
    after = read_ok(daq)
    after += advance_and_read(daq, clock, 5)
    got += after
    check_against_truth(got, emu)
    first = next(s for s in got if s.epoch == 1)
    assert first.restarted and first.counter == first.missed
    assert daq.sequencer.restarts_detected == 1
    with emu.lock:
        latched = emu.device.status & ldq412.STATUS_RESTART
    if transport == "ascii":
        assert latched and daq.clear_restart() is False
        assert first.missed == first.counter64 > 0
    else:
        assert not latched  # the driver cleared it after reporting it
        assert_fifo_delivered(got, emu, daq, boot=1)  # boot 0's last went with the power


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_channel_faults(emu_factory, transport: str) -> None:
    emu, daq, clock = emu_factory(transport)
    step = 1 if transport == "ascii" else 25
    got: list[Scan] = []

    def run(n: int) -> None:
        for _ in range(n):
            nonlocal got
            got += advance_and_read(daq, clock, step)

    run(3)
    emu.faults.sensor_fault(2, True)
    emu.faults.saturate(3, "high")
    emu.faults.stuck_channel(4, 0)
    run(3)
    last = got[-1]
    assert last.fault == (False, True, False, False)
    assert last.rail == (False, True, True, True)
    assert last.codes[1:] == (4095, 4095, 0)
    emu.faults.saturate(3, "low")
    emu.faults.stuck_channel(4, 1234)
    run(3)
    assert got[-1].codes[2:] == (0, 1234) and got[-1].rail == (False, True, True, False)
    emu.faults.clear()
    run(3)
    assert got[-1].trustworthy == (True, True, True, True)
    check_against_truth(got, emu)  # includes per-scan rail and fault bits


# --------------------------------------------------------------------------- FIFO specifics


@pytest.mark.parametrize("transport", MODBUS)
def test_fifo_overflow_is_reported_and_the_fifo_is_never_cleared(emu_factory, transport) -> None:
    emu, daq, clock = emu_factory(transport)
    got = advance_and_read(daq, clock, 10)
    got += advance_and_read(daq, clock, 300)
    lost = 300 - ldq412.FIFO_DEPTH
    check_against_truth(got, emu)
    first = got[11]
    assert first.overflow and first.missed == lost
    assert sum(s.overflow for s in got) == 1
    assert len(got) == 11 + ldq412.FIFO_DEPTH
    with emu.lock:  # clearing the flag would have emptied the FIFO: it stays latched
        assert emu.device.status & ldq412.STATUS_OVERFLOW
    more = advance_and_read(daq, clock, 30)
    assert len(more) == 30 and not any(s.overflow or s.missed for s in more)
    # a second overflow, with the flag still latched from the first: told by the gap
    again = advance_and_read(daq, clock, 270)
    assert again[0].overflow and again[0].missed == 270 - ldq412.FIFO_DEPTH
    check_against_truth(got + more + again, emu)


def test_connect_to_a_long_running_module_with_wraps(emu_factory) -> None:
    """Counter about to wrap (module up ~248 days at 200 Hz): the first read returns the
    256 buffered scans with the overflow latched; counter and device time unwrap."""
    uptime = (ldq412.U32_MOD - 600) / RATE
    emu, daq, clock = emu_factory("modbus-tcp", initial_uptime_s=uptime)
    got = daq.read_scans()
    assert len(got) == ldq412.FIFO_DEPTH and got[0].overflow
    for _ in range(40):
        got += advance_and_read(daq, clock, 20)
    check_against_truth(got, emu)
    assert got[0].counter64 < ldq412.U32_MOD < got[-1].counter64
    assert got[-1].counter < 1000
    # the device time wrapped many times before; its unwrapped value is still exact
    assert all(s.time64_us == s.counter64 * 5000 for s in got)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_device_time_wrap(emu_factory, transport: str) -> None:
    uptime = ldq412.U32_MOD / 1e6 - 0.5  # 32-bit µs wrap 0.5 s after connect
    emu, daq, clock = emu_factory(transport, initial_uptime_s=uptime)
    step = 1 if transport == "ascii" else 20
    got: list[Scan] = []
    for _ in range(200 // step * 2):
        got += advance_and_read(daq, clock, step)
    check_against_truth(got, emu)
    assert got[0].time_us > got[-1].time_us  # wrapped
    assert all(s.time64_us == s.counter64 * 5000 for s in got)


# --------------------------------------------------------------------------- configuration


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_scan_rate_change_keeps_times_exact(emu_factory, transport: str) -> None:
    emu, daq, clock = emu_factory(transport)
    step = 1 if transport == "ascii" else 15
    got: list[Scan] = []
    assert daq.scan_rate_hz == RATE  # what the driver works with, without a request
    for _ in range(10):
        got += advance_and_read(daq, clock, step)
    daq.write_scan_rate(50)
    assert daq.read_scan_rate() == 50 and daq.scan_rate_hz == 50
    for _ in range(10):
        clock.advance(step / 50)
        got += daq.read_scans()
    check_against_truth(got, emu)
    with pytest.raises(ValueError):
        daq.write_scan_rate(0)
    with pytest.raises(ValueError):
        daq.write_scan_rate(201)
    with pytest.raises(TypeError):
        daq.write_scan_rate(50.0)
    assert daq.read_scan_rate() == 50  # nothing written
    assert not hasattr(DAQ, "scan_rate")  # a request on the wire is a method call, not an attribute


@pytest.mark.parametrize("transport", MODBUS)
def test_modbus_exceptions_are_typed(emu_factory, transport: str) -> None:
    emu, daq, clock = emu_factory(transport)
    assert isinstance(daq, ModbusDAQ)
    with pytest.raises(DAQModbusException) as exc:
        daq.read_input_registers(100, 1)
    assert exc.value.code == 2
    with pytest.raises(DAQModbusException) as exc:
        daq.write_register(ldq412.HR_OVERSAMPLING, 3)
    assert exc.value.code == 3
    with pytest.raises(DAQModbusException) as exc:
        daq.write_register(ldq412.HR_COUNT, 1)
    assert exc.value.code == 2
    with pytest.raises(ValueError):
        daq.write_oversampling(3)
    daq.write_oversampling(4)
    assert daq.read_oversampling() == 4
    check_against_truth(advance_and_read(daq, clock, 10), emu)


def test_snapshot_polling_mode_and_snapshot(emu_factory) -> None:
    emu, daq, clock = emu_factory("modbus-tcp")
    poll = open_daq(emu.url + "&fifo=0", timeout=OK_TIMEOUT)
    try:
        clock.advance(5 * PERIOD)
        s = daq.snapshot()
        assert s == emu.truth[-1] or (s.counter, s.codes) == (
            emu.truth[-1].counter,
            emu.truth[-1].codes,
        )
        assert s.time_measured and s.status_measured
        got = []
        for _ in range(20):
            got += advance_and_read(poll, clock, 3)
        check_against_truth(got, emu)
        assert all(s.missed == 2 for s in got[1:])
        # the FIFO reader was not disturbed by the snapshot and the poller
        fifo = daq.read_scans()
        assert_fifo_delivered(fifo, emu, daq)
    finally:
        poll.close()


def test_ascii_checksum_mode(emu_factory) -> None:
    emu, daq, clock = emu_factory("ascii", TIMEOUT, ascii_checksum=True)
    assert "checksum=1" in emu.url
    got = advance_and_read(daq, clock, 1)
    emu.faults.corrupt_next(1)
    clock.advance(PERIOD)
    with pytest.raises(DAQProtocolError, match="checksum"):
        daq.read_scans()
    got += advance_and_read(daq, clock, 1)
    check_against_truth(got, emu)
    daq.close()  # the port is one program's at a time (opened exclusively)
    with pytest.raises(DAQTimeout):  # module ignores frames without a valid checksum
        open_daq(emu.url.replace("checksum=1", "checksum=0"), timeout=TIMEOUT)
