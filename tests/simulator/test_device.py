"""The LDQ-412 device model and clocks, without any wire (pure, fast)."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from loopcal.drivers.ldq412 import (
    CODE_MAX,
    FIFO_DEPTH,
    FIFO_FILLER,
    STATUS_OVERFLOW,
    STATUS_RESTART,
    U32_MOD,
    join_u32,
)
from loopcal.simulator.clock import ManualClock, SimClock
from loopcal.simulator.device import (
    LDQ412,
    DeviceOffError,
    scans_due,
)
from loopcal.simulator.registers import ILLEGAL_ADDRESS, ILLEGAL_VALUE, DeviceError
from loopcal.simulator.source import ConstantSource, TestSource
from tests.support.emulator import mid_volts

S = 1_000_000_000  # ns per second


def datasheet_code(v: float) -> int:
    """The datasheet's transfer function, written out in plain Python."""
    return min(max(math.floor((v + 10.0) * 4096 / 20.0), 0), 4095)


class RecordingSource:
    """Returns scripted volts (cycling) and records every instant array it was given."""

    def __init__(self, volts_cycle: list[list[float]]) -> None:
        self.volts_cycle = [np.asarray(v, dtype=float) for v in volts_cycle]
        self.calls: list[np.ndarray] = []

    def convert(self, t: np.ndarray) -> np.ndarray:
        self.calls.append(np.array(t))
        return self.volts_cycle[(len(self.calls) - 1) % len(self.volts_cycle)]


def const_device(codes=(2048, 1, 4095, 3000), **kw) -> LDQ412:
    return LDQ412(ConstantSource([mid_volts(c) for c in codes]), **kw)


# ---------------------------------------------------------------- conversion


def test_transfer_function_matches_datasheet_formula_bit_for_bit():
    rng = np.random.default_rng(3)
    # random volts, exact code boundaries (and one ulp either side), and beyond the rails
    bounds = [-10.0 + k * 20.0 / 4096 for k in range(0, 4097, 97)]
    volts = list(rng.uniform(-10.5, 10.5, 300))
    volts += bounds + [np.nextafter(b, -np.inf) for b in bounds] + [-10.0, 10.0, -11.0, 12.0]
    for i in range(0, len(volts), 4):
        chunk = (volts[i : i + 4] + [0.0] * 4)[:4]
        dev = LDQ412(ConstantSource(chunk))
        assert dev.latest.codes == tuple(datasheet_code(v) for v in chunk)


def test_rail_bits_for_codes_0_and_4095_only():
    dev = LDQ412(ConstantSource([-10.2, 10.7, mid_volts(1), mid_volts(4094)]))
    assert dev.latest.codes == (0, 4095, 1, 4094)
    assert dev.status & 0xFF == 0b0011


def test_oversampling_is_mean_rounded_half_up_and_calls_source_n_times():
    src = RecordingSource([[mid_volts(100)] * 4, [mid_volts(101)] * 4])
    clock = ManualClock()
    dev = LDQ412(src, scan_rate_hz=10)
    assert len(src.calls) == 1  # oversampling 1: one conversion for scan 0
    dev.write_registers(1, [2])
    clock.advance(0.1)
    dev.sync(clock.now_ns())
    # conversions 101, 100 -> mean 100.5 -> rounded half up to 101 (truncation gives 100)
    assert len(src.calls) == 3
    assert dev.latest.codes == (101,) * 4
    # all conversions of one scan see the same instants (burst at the channel instant)
    np.testing.assert_array_equal(src.calls[1], src.calls[2])

    src4 = RecordingSource([[mid_volts(100)] * 4] * 3 + [[mid_volts(101)] * 4])
    dev4 = LDQ412(src4, scan_rate_hz=10)
    dev4.write_registers(1, [4])
    dev4.sync(100_000_000)  # scan 1 = calls 2..5: 100, 100, 101, 100 -> 100.25 -> 100
    assert len(src4.calls) == 5
    assert dev4.latest.codes == (100,) * 4


def test_oversampling_rounding_three_quarters_goes_up():
    src = RecordingSource([[mid_volts(200)] * 4] + [[mid_volts(201)] * 4] * 3)
    dev = LDQ412(src, scan_rate_hz=10)  # scan 0 consumed call 1 (200)
    dev.write_registers(1, [4])
    dev.sync(100_000_000)  # calls 2..5: 201, 201, 201, 200 -> 200.75 -> 201
    assert dev.latest.codes == (201,) * 4


# ---------------------------------------------------------------- scanning


def test_scan_schedule_counter_time_and_channel_instants():
    src = RecordingSource([[0.0] * 4])
    dev = LDQ412(src, scan_rate_hz=20)
    dev.sync(1 * S)
    truth = dev.truth
    assert [s.counter for s in truth] == list(range(21))
    assert [s.time_us for s in truth] == [k * 50_000 for k in range(21)]
    assert len(src.calls) == 21
    np.testing.assert_allclose(src.calls[3], 0.15 + np.arange(4) * 250e-6, rtol=0, atol=1e-12)
    dev.sync(1 * S + 49_999_000)  # one microsecond short of the next scan
    assert len(dev.truth) == 21
    dev.sync(1 * S + 50_000_000)
    assert dev.truth[-1].counter == 21


def test_non_integer_period_has_no_drift():
    dev = const_device(scan_rate_hz=3)
    dev.sync(10 * S)
    # scan j at floor(j * 1e6 / 3) us: exactly 31 scans in [0, 10 s], the last at 10 s
    assert [s.time_us for s in dev.truth][-2:] == [9_666_666, 10_000_000]
    assert len(dev.truth) == 31


def test_rate_change_reanchors_schedule_at_the_write():
    dev = const_device(scan_rate_hz=20)
    dev.sync(120_000_000)  # scans at 0, 50, 100 ms
    dev.write_registers(0, [50])
    dev.sync(1 * S)
    times = [s.time_us for s in dev.truth]
    assert times[:5] == [0, 50_000, 100_000, 140_000, 160_000]
    dev.sync(1_010_000_000)
    dev.write_registers(0, [50])  # same value, off the grid: schedule untouched
    dev.sync(1_020_000_000)
    assert dev.truth[-1].time_us == 1_020_000  # a re-anchor would have put it at 1.03 s
    assert dev.holding_registers()[0] == 50


def test_truth_records_every_scan_with_status():
    dev = const_device(codes=(0, 5, 6, 7), scan_rate_hz=200)
    dev.sync(2 * S)
    counters = [s.counter for s in dev.truth]
    assert counters == list(range(401))
    assert all(s.status & 0x0F == 0b0001 for s in dev.truth)  # channel 1 at the rail
    # the overflow latch shows from the first scan that overflowed the FIFO
    assert not dev.truth[FIFO_DEPTH - 1].status & STATUS_OVERFLOW
    assert dev.truth[FIFO_DEPTH].status & STATUS_OVERFLOW


# ---------------------------------------------------------------- FIFO


def test_fifo_overflow_drops_oldest_and_latches():
    dev = const_device(scan_rate_hz=200)
    dev.sync(2 * S)  # 401 scans
    assert dev.fifo_level == FIFO_DEPTH
    assert dev.status & STATUS_OVERFLOW
    regs = dev.read_input_registers(256, 120)
    counters = [join_u32(regs[i], regs[i + 1]) for i in range(0, 120, 6)]
    assert counters == list(range(401 - 256, 401 - 256 + 20))
    assert regs[2:6] == [2048, 1, 4095, 3000]
    assert dev.fifo_level == FIFO_DEPTH - 20
    assert dev.status & STATUS_OVERFLOW  # latched, not cleared by reading
    dev.write_registers(2, [1])
    assert dev.fifo_level == 0 and not dev.status & STATUS_OVERFLOW


def test_fifo_read_beyond_waiting_gives_filler_and_empties():
    dev = const_device(scan_rate_hz=20)
    dev.sync(100_000_000)  # scans 0, 1, 2
    assert dev.fifo_level == 3
    regs = dev.read_input_registers(256, 5 * 6)
    assert [join_u32(regs[i], regs[i + 1]) for i in (0, 6, 12)] == [0, 1, 2]
    assert regs[18:] == [FIFO_FILLER] * 12
    assert dev.fifo_level == 0
    assert dev.read_input_registers(256, 6) == [FIFO_FILLER] * 6


@pytest.mark.parametrize(
    ("address", "count", "code"),
    [
        (256, 7, ILLEGAL_VALUE),  # not a multiple of 6
        (256, 1, ILLEGAL_VALUE),
        (256, 0, ILLEGAL_VALUE),  # Modbus quantity 0
        (256, 126, ILLEGAL_VALUE),  # Modbus quantity > 125
        (256, 126 - 6, None),  # 20 scans: fine
        (256, 121, ILLEGAL_ADDRESS),  # past the window's last register 375
        (256, 125, ILLEGAL_ADDRESS),
        (262, 6, ILLEGAL_ADDRESS),  # inside the window, not at its start
        (10, 1, ILLEGAL_ADDRESS),
        (0, 11, ILLEGAL_ADDRESS),
        (9, 2, ILLEGAL_ADDRESS),
        (255, 1, ILLEGAL_ADDRESS),
        (511, 2, ILLEGAL_ADDRESS),
        (515, 2, ILLEGAL_ADDRESS),
        (516, 1, ILLEGAL_ADDRESS),
        (65535, 1, ILLEGAL_ADDRESS),
    ],
)
def test_input_register_exceptions_and_no_pop_on_error(address, count, code):
    dev = const_device(scan_rate_hz=200)
    dev.sync(1 * S)
    level = dev.fifo_level
    if code is None:
        assert len(dev.read_input_registers(address, count)) == count
        return
    with pytest.raises(DeviceError) as err:
        dev.read_input_registers(address, count)
    assert err.value.code == code
    assert dev.fifo_level == level


def test_snapshot_and_identity_registers():
    dev = const_device(serial_number=0x12345678, firmware=(3, 7), scan_rate_hz=20)
    dev.sync(250_000_000)  # 6 scans: counter 5 at 250 ms
    regs = dev.read_input_registers(0, 10)
    assert regs == [0, 5, 0x0003, 0xD090, 2048, 1, 4095, 3000, STATUS_RESTART | 0x0004, 6]
    assert dev.read_input_registers(4, 3) == [2048, 1, 4095]
    assert dev.read_input_registers(512, 4) == [0x0412, 0x0307, 0x1234, 0x5678]
    assert dev.read_input_registers(514, 2) == [0x1234, 0x5678]
    assert dev.firmware_text == "3.07"


# ---------------------------------------------------------------- holding registers


def test_holding_registers_defaults_writes_and_exceptions():
    dev = const_device(scan_rate_hz=20, ascii_checksum=True)
    assert dev.read_holding_registers(0, 5) == [20, 1, 0, 0, 1]
    for reg, bad in [(0, 0), (0, 201), (1, 3), (1, 32), (2, 2), (3, 7), (4, 2)]:
        with pytest.raises(DeviceError) as err:
            dev.write_registers(reg, [bad])
        assert err.value.code == ILLEGAL_VALUE
    with pytest.raises(DeviceError) as err:
        dev.write_registers(4, [0, 0])  # register 5 does not exist
    assert err.value.code == ILLEGAL_ADDRESS
    with pytest.raises(DeviceError) as err:
        dev.read_holding_registers(3, 3)
    assert err.value.code == ILLEGAL_ADDRESS
    # all-or-nothing: a bad value anywhere applies nothing
    with pytest.raises(DeviceError):
        dev.write_registers(0, [100, 8, 0, 0, 5])
    assert dev.read_holding_registers(0, 5) == [20, 1, 0, 0, 1]
    dev.write_registers(0, [100, 16, 0, 1, 0])
    assert dev.read_holding_registers(0, 5) == [100, 16, 0, 0, 0]
    assert not dev.status & STATUS_RESTART
    for choice in (1, 2, 4, 8, 16):
        dev.write_registers(1, [choice])
        assert dev.oversampling == choice


# ---------------------------------------------------------------- faults and power


def test_sensor_fault_stuck_and_saturation():
    dev = const_device(codes=(100, 200, 300, 400), scan_rate_hz=10)
    dev.set_sensor_fault(2, True)
    dev.set_stuck(3, 1234)
    dev.set_saturation(4, "low")
    dev.sync(100_000_000)
    assert dev.latest.codes == (100, CODE_MAX, 1234, 0)
    assert dev.status & 0xFF == 0x20 | 0x02 | 0x08  # fault ch2; rail ch2 and ch4
    dev.set_saturation(4, "high")
    dev.set_stuck(3, 0)
    dev.sync(200_000_000)
    assert dev.latest.codes == (100, CODE_MAX, 0, CODE_MAX)
    assert dev.status & 0xFF == 0x20 | 0x02 | 0x04 | 0x08
    dev.clear_channel_faults()
    dev.sync(300_000_000)
    assert dev.latest.codes == (100, 200, 300, 400)
    assert dev.status & 0xFF == 0
    with pytest.raises(ValueError):
        dev.set_stuck(5, 0)
    with pytest.raises(ValueError):
        dev.set_saturation(1, "sideways")


def test_power_cycle_is_silent_then_power_on_state():
    src = RecordingSource([[mid_volts(7)] * 4])
    dev = LDQ412(src, scan_rate_hz=20, ascii_checksum=False)
    dev.write_registers(0, [100, 4, 0, 1, 1])
    dev.set_stuck(1, 99)
    dev.sync(1 * S)
    n_before = len(dev.truth)
    dev.power_cycle()
    assert not dev.powered
    with pytest.raises(DeviceOffError):
        dev.read_input_registers(0, 10)
    dev.sync(2_999_999_999)
    assert not dev.powered and len(dev.truth) == n_before
    dev.sync(3 * S)
    assert dev.powered
    first = dev.truth[n_before]
    assert (first.counter, first.time_us, first.boot) == (0, 0, 1)
    assert first.t_s == pytest.approx(3.0)  # source time keeps running through the cycle
    assert first.codes == (99, 7, 7, 7)  # channel faults are physical: they survive
    assert dev.status & STATUS_RESTART
    assert dev.fifo_level == 1
    assert dev.read_holding_registers(0, 5) == [20, 1, 0, 0, 0]


def test_initial_uptime_wraps_counter_and_time():
    rate = 200
    # powered on 1 ms after the scan with counter 2**32 - 3 (period 5 ms)
    uptime_s = (U32_MOD - 3) / rate + 0.001
    dev = const_device(scan_rate_hz=rate, initial_uptime_s=uptime_s)
    assert dev.latest.counter == U32_MOD - 3
    assert dev.fifo_level == FIFO_DEPTH and dev.status & STATUS_OVERFLOW
    assert len(dev.truth) == FIFO_DEPTH  # only the scans still in the FIFO exist
    dev.sync(4 * 5_000_000)  # four more scans
    assert [s.counter for s in dev.truth[-5:]] == [U32_MOD - 3, U32_MOD - 2, U32_MOD - 1, 0, 1]
    times = [s.time_us for s in dev.truth]
    expected = [(j * 1_000_000 // rate) % U32_MOD for j in range(U32_MOD - 258, U32_MOD + 2)]
    assert times == expected
    assert all(0 <= t < U32_MOD for t in times)
    assert scans_due(0, 20) == 1 and scans_due(49_999, 20) == 1 and scans_due(50_000, 20) == 2


def test_time_wraps_after_71_6_minutes():
    dev = const_device(scan_rate_hz=1, initial_uptime_s=4294.0)
    assert dev.latest.time_us == 4_294_000_000
    dev.sync(1 * S)
    assert dev.latest.time_us == 4_295_000_000 - U32_MOD


def test_test_source_is_deterministic_per_seed():
    t = np.array([1.0, 1.00025, 1.0005, 1.00075])
    a, b, c = TestSource(5), TestSource(5), TestSource(6)
    va = [a.convert(t) for _ in range(3)]
    vb = [b.convert(t) for _ in range(3)]
    vc = [c.convert(t) for _ in range(3)]
    np.testing.assert_array_equal(va, vb)
    assert not np.array_equal(va, vc)
    assert np.all(np.abs(np.asarray(va)) < 9.0)
    assert abs(va[0] - a.clean(t)).max() < 0.05


# ---------------------------------------------------------------- clocks


def test_manual_clock_is_exact_and_monotonic():
    clock = ManualClock()
    for _ in range(10):
        clock.advance(0.1)
    assert clock.now_ns() == S
    assert clock.now() == 1.0
    with pytest.raises(ValueError):
        clock.advance(-0.001)


def test_sim_clock_runs_speed_times_wall_time():
    # wall times read around its creation and around the reading: exact bounds, whatever
    # the machine's load does between two lines
    t0 = time.monotonic_ns()
    sim = SimClock(50.0)
    t1 = time.monotonic_ns()
    time.sleep(0.05)
    t2 = time.monotonic_ns()
    s = sim.now_ns()
    t3 = time.monotonic_ns()
    assert 50 * (t2 - t1) <= s <= 50 * (t3 - t0)
    with pytest.raises(ValueError):
        SimClock(0)


def test_truth_limit_keeps_the_latest_scans_only():
    dev = const_device(scan_rate_hz=200, truth_limit=100)
    dev.sync(5 * S)  # 1001 scans
    assert 100 <= len(dev.truth) < 200
    assert dev.truth[-1].counter == 1000
    assert [s.counter for s in dev.truth] == list(range(1001 - len(dev.truth), 1001))
