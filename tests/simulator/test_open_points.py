"""The emulator's settings for what the datasheet leaves open (simulator/open_points.py):
each does what it says, on the device model and on the wire, and the defaults are the
emulator as it was."""

from __future__ import annotations

import json
import statistics
import time

import pytest
import serial
from pymodbus.client import ModbusTcpClient

from loopcal.drivers.ldq412 import FIFO_FILLER, IR_FIFO, join_u32
from loopcal.simulator.clock import ManualClock
from loopcal.simulator.device import (
    LDQ412,
    DeviceOffError,
)
from loopcal.simulator.emulator import Emulator
from loopcal.simulator.open_points import DATASHEET_LINES, Latency, OpenPoints
from loopcal.simulator.registers import ILLEGAL_ADDRESS, ILLEGAL_VALUE, DeviceError
from tests.support.emulator import golden_source
from tests.support.processes import loopcal

S = 1_000_000_000


def device(op: OpenPoints, **kw) -> LDQ412:
    return LDQ412(golden_source(), open_points=op, **kw)


def test_defaults_are_the_emulator_as_it_was():
    assert OpenPoints().changed() == {}
    a, b = LDQ412(golden_source()), device(OpenPoints())
    for dev in (a, b):
        dev.sync(3 * S + 7)
    assert [(t.counter, t.time_us, t.t_s) for t in a.truth] == [
        (t.counter, t.time_us, t.t_s) for t in b.truth
    ]
    assert set(DATASHEET_LINES) == set(OpenPoints.__dataclass_fields__)


def test_scan_zero_comes_at_the_phase_and_the_module_is_silent_before():
    dev = device(OpenPoints(scan_phase_us=1809))
    dev.sync(1_808_000)
    assert not dev.ready and dev.truth == []
    with pytest.raises(DeviceOffError):
        dev.read_input_registers(0, 10)
    dev.sync(1_809_000)
    assert dev.ready and [t.time_us for t in dev.truth] == [1809]
    dev.sync(S + 1_809_000)
    assert [t.time_us for t in dev.truth][-2:] == [951_809, 1_001_809]
    dev.power_cycle(1.75)  # again after a power cycle
    dev.sync(S + 1_809_000 + 1_750_000_000 + 1_808_999)
    assert not dev.ready
    dev.sync(S + 1_809_000 + 1_750_000_000 + 1_809_000)
    assert dev.truth[-1].counter == 0 and dev.truth[-1].boot == 1


@pytest.mark.slow
@pytest.mark.parametrize("ppm", [200.0, -200.0, 1000.0])
def test_a_clock_error_changes_the_rate_against_the_host_not_the_device_times(ppm):
    dev = device(OpenPoints(clock_ppm=ppm))
    dev.sync(600 * S)  # ten minutes of the host's clock
    t = dev.truth
    assert all(s.time_us == (s.counter * 50_000) % (1 << 32) for s in t)  # its own µs
    assert len(t) == 1 + int(12_000 * (1 + ppm * 1e-6) + 1e-6)  # 20 Hz by its own clock
    last = t[-1]
    assert dev.host_ns(0, last.counter * 50_000) == pytest.approx(
        last.counter * 50e6 / (1 + ppm * 1e-6), abs=1
    )
    assert last.t_s == pytest.approx(last.counter * 0.05 / (1 + ppm * 1e-6), abs=1e-9)


def test_fifo_underrun_filler_or_short():
    for mode, expect in (("filler", 3 * 6), ("short", 2 * 6)):
        dev = device(OpenPoints(fifo_underrun=mode))
        dev.sync(50_000_000)  # scans 0 and 1
        regs = dev.read_input_registers(IR_FIFO, 18)
        assert len(regs) == expect
        assert [join_u32(*regs[0:2]), join_u32(*regs[6:8])] == [0, 1]
        assert regs[12:] == [FIFO_FILLER] * (expect - 12)
        assert dev.read_input_registers(IR_FIFO, 6) == ([] if mode == "short" else [0xFFFF] * 6)


def test_read_limits_refuse_or_truncate():
    dev = device(OpenPoints(max_read_registers=64))
    dev.sync(S)
    with pytest.raises(DeviceError) as exc:
        dev.read_input_registers(IR_FIFO, 120)
    assert exc.value.code == ILLEGAL_VALUE and dev.fifo_level == 21  # nothing taken
    assert len(dev.read_input_registers(IR_FIFO, 60)) == 60
    dev = device(OpenPoints(max_read_registers=64, over_limit="truncate"))
    dev.sync(S)
    regs = dev.read_input_registers(IR_FIFO, 120)
    assert len(regs) == 60 and dev.fifo_level == 11  # ten whole scans; the rest waits
    assert len(dev.read_input_registers(512, 4)) == 4


def test_holes_and_snapshot_reads():
    strict = device(OpenPoints(snapshot_reads="whole"))
    strict.sync(0)
    assert len(strict.read_input_registers(0, 10)) == 10
    with pytest.raises(DeviceError) as exc:
        strict.read_input_registers(8, 2)
    assert exc.value.code == ILLEGAL_ADDRESS
    default = device(OpenPoints())
    default.sync(0)
    with pytest.raises(DeviceError):
        default.read_input_registers(0, 12)  # spans a hole
    lax = device(OpenPoints(holes="zero"))
    lax.sync(0)
    regs = lax.read_input_registers(0, 12)
    assert regs[:10] == lax.snapshot_registers() and regs[10:] == [0, 0]
    regs = lax.read_input_registers(250, 12)  # into the FIFO window: takes nothing
    assert regs == [0] * 6 + [FIFO_FILLER] * 6 and lax.fifo_level == 1


def _rtt(send, n: int = 40) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.monotonic()
        send()
        out.append(time.monotonic() - t0)
    return out


@pytest.mark.slow
def test_latency_on_the_wire():
    """Answers wait the drawn delay: at least the minimum, about the datasheet's spread."""
    op = OpenPoints(latency=Latency(min_ms=4.0, max_ms=10.0))
    with Emulator("ascii", golden_source(), clock=ManualClock(), open_points=op) as emu:
        # a loaded machine has held a pty's answer 5.5 s (tests/support/drivers.py): the
        # median below is the bound, and a stalled answer must still come
        port = serial.Serial(emu.url.split("://")[1].split("?")[0], 115200, timeout=10.0)

        def ask() -> None:
            port.write(b"#01\r")
            assert port.read_until(b"\r").startswith(b">")

        ascii_rtt = _rtt(ask)
        port.close()
    with Emulator("modbus-tcp", golden_source(), clock=ManualClock(), open_points=op) as emu:
        client = ModbusTcpClient("127.0.0.1", port=emu.port, timeout=1.0)
        client.connect()
        tcp_rtt = _rtt(lambda: client.read_input_registers(0, count=10, device_id=1))
        client.close()
    for rtt in (ascii_rtt, tcp_rtt):
        assert min(rtt) >= 0.004  # never sooner than the minimum
        assert 0.005 < statistics.median(rtt) < 0.050  # about 7 ms, whatever the load


def test_slow_answers_come_late_but_come():
    op = OpenPoints(latency=Latency(min_ms=0, max_ms=0, slow_fraction=1.0, slow_ms=(50, 60)))
    with Emulator("modbus-tcp", golden_source(), clock=ManualClock(), open_points=op) as emu:
        client = ModbusTcpClient("127.0.0.1", port=emu.port, timeout=1.0)
        client.connect()
        rtt = _rtt(lambda: client.read_input_registers(0, count=10, device_id=1), n=5)
        client.close()
    assert min(rtt) >= 0.050


@pytest.mark.slow
def test_loopcal_simulate_takes_the_settings_and_names_them(tmp_path):
    args = ["simulate", "--duration", "0.3", "--scan-phase-us", "1809", "--clock-ppm", "-150",
            "--latency", "datasheet", "--slow-answers", "0.01", "--fifo-underrun", "short",
            "--max-read-registers", "60", "--over-limit", "truncate", "--holes", "zero",
            "--snapshot-reads", "whole", "--truth-out"]  # fmt: skip
    out = tmp_path / "truth.jsonl"
    proc = loopcal(*args, out, timeout=60)
    assert proc.returncode == 0, proc.stderr
    header, first = (json.loads(line) for line in out.read_text().splitlines()[:2])
    assert set(header["open_points"]) == {
        "scan_phase_us", "clock_ppm", "latency", "fifo_underrun", "max_read_registers",
        "over_limit", "holes", "snapshot_reads",
    }  # fmt: skip
    assert first["time_us"] == 1809
    bad = loopcal(*args[:3], "--slow-answers", "0.1", timeout=60)
    assert bad.returncode == 2 and "--slow-answers needs --latency" in bad.stderr


@pytest.mark.parametrize("transport", ["modbus-tcp", "ascii"])
def test_a_held_clock_starts_at_the_first_request_though_scan_zero_is_late(transport):
    """``--wait-for-client`` with scan 0 after power-on: the first request starts the clock
    although the module cannot answer it yet (it used to be dropped unnoted over Modbus,
    and the module stayed silent for ever); a driver's next tries get answers."""
    from loopcal.drivers import DAQError, open_daq
    from loopcal.simulator.clock import HeldClock

    clock = HeldClock()
    op = OpenPoints(scan_phase_us=1809)
    with Emulator(transport, golden_source(), clock=clock, open_points=op) as emu:
        answered = None
        for _ in range(10):
            try:
                with open_daq(emu.url, timeout=0.1) as daq:
                    answered = daq.read_scans()
                break
            except DAQError:
                time.sleep(0.05)
        assert clock.now_ns() > 0
        assert answered and all(s.time64_us % 50_000 == 1809 for s in answered), answered
