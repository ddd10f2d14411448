"""``probe``: the module found and read without changing it, or each cause of not finding
it shown on a real part (a closed port, a listener that never accepts, servers of other
protocols, a Modbus device of another model, the emulator at another unit id, ASCII
address, checksum mode or line rate, a line where another device talks, a missing
device, a port another process holds, a serial device server's TCP port that refuses);
and ``diagnose``, the recorder's words for a driver's error.

Every probe must end within its budget, read from its own report (``elapsed_s``). The
bound is the design's: a try is started only while twice its answer timeout and a margin
(``MARGIN_S``) are left, and a try that gets no answer takes one timeout, so the last ends
with at least one timeout and the margin in hand. The tries that must get an answer from
the emulator in this process wait 3 s for it, within three times the default budget,
which makes the same tries as 1 s within the default; at 1 s a probe found no answer at
the module's own rate once under two CPU hogs. A loaded machine has held a
pseudo-terminal's bytes back for 5.5 s (tests/support/drivers.py): a serial module is
served behind the emulated device server (``tcp_line``) but where the tty is the subject
(its rate, a port held), and a try there that must get an answer waits 6 s (ci66: none
came at the module's own rate within 3 s). The probes that use
their whole budget wait 0.5 s, so that 0.75 s of slack absorbs a busy machine's
scheduling delays.
"""

from __future__ import annotations

import pytest

from loopcal.drivers import DAQDisconnected, driver_for_url, ldq412, open_daq
from loopcal.drivers.diagnosis import CAUSES, diagnose, errno_of, serial_ports
from loopcal.drivers.errors import DAQError
from loopcal.drivers.probe import PROBE_BUDGET_S, ProbeReport, probe
from loopcal.simulator.clock import ManualClock
from loopcal.simulator.emulator import Emulator
from tests.support.drivers import tcp_line
from tests.support.processes import free_port
from tests.support.servers import (
    other_modbus_device,
    port_holder,
    talking_line,
    tcp_server,
    unanswered_port,
)

OK_TIMEOUT = 3.0  # answers the emulator must give (module docstring)
PTY_TIMEOUT = 6.0  # ... on a pseudo-terminal (module docstring)
FULL_TIMEOUT = 0.5  # probes that use their whole budget


def _probe(url: str, timeout: float = OK_TIMEOUT) -> ProbeReport:
    """probe() within the default budget, or, for a timeout over 1 s, that many times it
    (the same tries as 1 s within the default)."""
    budget = PROBE_BUDGET_S * max(1.0, timeout)
    report = probe(url, timeout=timeout, budget=budget)
    assert report.elapsed_s <= budget, report
    assert report.cause is None or report.cause in CAUSES
    return report


@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu", "ascii"])
def test_the_module_is_found_read_and_left_as_it_was(transport: str) -> None:
    with Emulator(transport, clock=ManualClock(), **tcp_line(transport)) as emu:
        emu.clock.advance(1.0)
        with emu.handle.synced() as device:
            level, status = device.fifo_level, device.status
        report = _probe(emu.url)
        last = emu.truth[-1]
        with emu.handle.synced() as device:  # nothing taken off the FIFO, no flag cleared
            assert (device.fifo_level, device.status) == (level, status)
    assert report.found and report.cause is None and report.answered_url == emu.url
    assert report.identity["model"] == "LDQ412" and report.identity["firmware"] == "2.01"
    modbus = transport != "ascii"
    assert report.identity["serial"] == (0x00C0FFEE if modbus else None)
    module = report.module
    assert module["scan_rate_hz"] == 20 and module["restarted"] and not module["overflow"]
    assert module["fifo_level"] == (level if modbus else None)
    scan = module["scan"]
    assert (scan["counter"], tuple(scan["codes"])) == (last.counter, last.codes)
    assert scan["volts"] == [round(float(ldq412.code_to_volts(c)), 4) for c in last.codes]
    assert report.rtt_ms["n"] == 5 and 0 < report.rtt_ms["median"] <= report.rtt_ms["max"]
    assert [a.outcome for a in report.tried] == ["answers"]
    assert report.notes == []  # no channel at the rail, answers well within the timeout


def test_a_closed_port_is_refused() -> None:
    port = free_port()
    report = _probe(f"modbus-tcp://127.0.0.1:{port}")
    assert report.cause == "refused" and not report.found
    assert report.message == f"nothing listens at 127.0.0.1:{port} (connection refused)"
    assert "502" in report.hint and len(report.tried) == 1


def test_a_host_that_does_not_answer_times_out() -> None:
    with unanswered_port() as port:
        report = _probe(f"modbus-tcp://127.0.0.1:{port}", timeout=0.25)
    assert report.cause == "timeout", report
    assert "does not answer (no TCP connection within 0.25 s)" in report.message


@pytest.mark.slow
@pytest.mark.parametrize(("kind", "words", "cause"), [
    ("http", "it sent b'HTTP/1.1 400 Bad Request", "not_modbus"),
    ("echo", "sends back what it is sent (an echo server)", "not_modbus"),
    ("close", "closes it on a Modbus request, with no answer", "closed"),
])  # fmt: skip
def test_a_server_of_another_protocol_is_named(kind: str, words: str, cause: str) -> None:
    with tcp_server(kind) as port:
        report = _probe(f"modbus-tcp://127.0.0.1:{port}")
    assert report.cause == cause and words in report.message, report.message
    assert len(report.tried) == 1  # no unit is scanned on a server that is not Modbus


@pytest.mark.slow
def test_a_server_that_never_answers_has_every_unit_tried_within_the_budget() -> None:
    with tcp_server("silent") as port:
        report = _probe(f"modbus-tcp://127.0.0.1:{port}?unit=5", timeout=FULL_TIMEOUT)
    assert report.cause == "no_answer", report
    units = [int(a.url.rsplit("unit=", 1)[1]) for a in report.tried]
    assert units[:3] == [5, 1, 2] and len(units) >= 6  # the URL's, the datasheet's, the rest
    assert all(a.outcome == "no answer" for a in report.tried)
    assert "the 5 s budget allowed no more" in report.message


@pytest.mark.parametrize(("model_code", "words"), [
    (0x1234, "its model code (input register 512) is 0x1234, not the LDQ-412's 0x0412"),
    (None, "refuses the LDQ-412's registers (Modbus exception 0x02)"),
])  # fmt: skip
def test_another_modbus_device_is_not_the_module(model_code: int | None, words: str) -> None:
    with other_modbus_device(model_code) as port:
        report = _probe(f"modbus-tcp://127.0.0.1:{port}")
    assert report.cause == "not_module" and words in report.message, report.message
    if model_code is not None:
        assert report.identity["model_code"] == model_code


@pytest.mark.slow
@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu"])
def test_a_unit_that_does_not_answer_names_the_one_that_does(transport: str) -> None:
    with Emulator(transport, clock=ManualClock(), **tcp_line(transport)) as emu:
        url = emu.url.replace("unit=1", "unit=5")
        report = _probe(url)
    assert report.cause == "wrong_unit" and not report.found
    assert report.message.startswith("unit 5 does not answer at ")
    assert report.message.endswith(f"; unit 1 does: use {emu.url}")
    assert report.answered_url == emu.url and report.identity["model"] == "LDQ412"
    assert [a.outcome for a in report.tried] == ["no answer", "answers"]


@pytest.mark.slow
def test_a_module_at_another_unit_is_found_by_scanning() -> None:
    with Emulator("modbus-tcp", clock=ManualClock(), unit=3) as emu:
        report = _probe(emu.url.replace("unit=3", "unit=1"))
    assert report.cause == "wrong_unit" and report.answered_url == emu.url
    assert [a.url.rsplit("=", 1)[1] for a in report.tried] == ["1", "2", "3"]


@pytest.mark.slow
@pytest.mark.parametrize(("given", "cause", "words"), [
    ("addr=05&checksum=0", "wrong_address", "address 05 does not answer at "),
    ("addr=01&checksum=1", "wrong_checksum", "with checksum on (bytes arrive, but no valid "
                                             "frame); the module answers with checksum off"),
])  # fmt: skip
def test_an_ascii_address_or_checksum_that_is_not_the_modules(
    given: str, cause: str, words: str
) -> None:
    with Emulator("ascii", clock=ManualClock(), **tcp_line("ascii")) as emu:
        report = _probe(emu.url.replace("addr=01&checksum=0", given))
    assert report.cause == cause and words in report.message, report.message
    assert report.answered_url == emu.url


def _option(url: str, key: str) -> object:
    cls, parsed = driver_for_url(url)
    return cls.url_options(parsed)[key]


@pytest.mark.slow
@pytest.mark.parametrize(("transport", "module", "given"), [
    ("modbus-rtu", 19200, 115200),  # the datasheet's rate, then the usual ones: 9600, 19200
    ("ascii", 115200, 9600),  # the other checksum mode, then the datasheet's rate
])  # fmt: skip
def test_a_rate_that_is_not_the_modules_names_the_one_that_answers(
    transport: str, module: int, given: int
) -> None:
    with Emulator(transport, clock=ManualClock(), baud=module) as emu:
        report = _probe(emu.url.replace(f"baud={module}", f"baud={given}"), PTY_TIMEOUT)
    assert report.cause == "wrong_baud", report
    assert f"{given} baud" in report.message
    assert report.message.endswith(f"the module answers with {module} baud: use {emu.url}")
    rates = [_option(a.url, "baud") for a in report.tried]
    assert rates[0] == given and rates[-1] == module and len(rates) == 3
    assert report.tried[-1].outcome == "answers" and report.answered_url == emu.url


@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["modbus-rtu", "ascii"])
def test_a_line_where_another_device_talks_is_garbled_at_every_rate(scheme: str) -> None:
    nmea = b"$GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,*47\r\n"
    with talking_line(9600, nmea) as path:
        report = _probe(f"{scheme}://{path}", timeout=FULL_TIMEOUT)
    assert report.cause == "garbled", report
    assert report.message.startswith(f"bytes arrive on {path}, but no valid frame at any ")
    rates = {_option(a.url, "baud") for a in report.tried}
    assert {115200, 9600} <= rates  # at the talker's own rate too: not our protocol
    # garbled wherever the talker's bytes came; a talker (a thread of this process) that a
    # loaded machine held through one rate's window leaves it silent, never answering
    outcomes = {a.outcome for a in report.tried}
    assert "garbled" in outcomes and outcomes <= {"garbled", "no answer"}, outcomes


def test_a_missing_device_lists_the_ports_there_are() -> None:
    report = _probe("modbus-rtu:///dev/ttyUSB-loopcal-none")
    assert report.cause == "no_device" and report.tried == []
    assert report.message.startswith("no such device /dev/ttyUSB-loopcal-none; serial ports here:")
    assert report.details["ports"] == serial_ports()
    assert "/dev/serial/by-id" in report.hint and "dmesg" in report.hint


def test_a_path_that_is_not_a_device() -> None:
    report = _probe("ascii:///etc/hostname")
    assert report.cause == "not_a_device"


@pytest.mark.parametrize("transport", ["modbus-rtu", "ascii"])
def test_a_port_another_process_holds_names_its_pid(transport: str) -> None:
    with Emulator(transport, clock=ManualClock()) as emu:
        path = emu.url.split("://", 1)[1].split("?", 1)[0]
        with port_holder(path) as pid:
            report = _probe(emu.url)
    assert report.cause == "busy" and report.tried == []
    assert f"{path} is held by another process (locked): pid {pid}" in report.message
    assert report.details["holders"][0]["pid"] == pid


# -- diagnose: the recorder's words for a driver's error (nothing sent) ---------------------


def _error(url: str, timeout: float = 0.25) -> DAQError:
    with pytest.raises(DAQError) as caught:
        open_daq(url, timeout=timeout)
    return caught.value


@pytest.mark.slow
def test_diagnose_names_the_cause_of_a_drivers_error() -> None:
    url = f"modbus-tcp://127.0.0.1:{free_port()}"
    assert diagnose(_error(url), url).cause == "refused"
    with unanswered_port() as port:
        url = f"modbus-tcp://127.0.0.1:{port}"
        assert diagnose(_error(url), url, timeout=0.25).cause == "timeout"
    with tcp_server("echo") as port:
        url = f"modbus-tcp://127.0.0.1:{port}"
        assert diagnose(_error(url), url).cause == "not_modbus"
    url = "modbus-rtu:///dev/ttyUSB-loopcal-none"  # the device is looked at
    found = diagnose(_error(url), url)
    assert found.cause == "no_device" and "no such device" in found.message
    with Emulator("modbus-tcp", clock=ManualClock()) as emu:
        url = emu.url.replace("unit=1", "unit=9")
        found = diagnose(_error(url), url, timeout=0.25)
    assert found.cause == "no_answer" and "unit 9 does not answer" in found.message
    assert "loopcal probe" in found.hint
    with talking_line(9600, b"hello\r\n") as path:
        url = f"modbus-rtu://{path}?baud=9600"
        # what the line brings is the subject: a read as long as a loaded machine has held a
        # pty's bytes back (ci55: nothing heard in 0.25 s, "no_answer")
        found = diagnose(_error(url, OK_TIMEOUT), url)
    assert found.cause == "garbled" and "9600 baud" in found.message


@pytest.mark.parametrize("scheme", ["ascii", "modbus-rtu"])
def test_a_device_server_that_refuses_is_named_by_its_host_and_port(scheme: str) -> None:
    port = free_port()  # bound, its number taken, closed: nothing listens there
    url = f"{scheme}://127.0.0.1:{port}"
    with pytest.raises(DAQDisconnected) as caught:
        open_daq(url, timeout=0.25)
    _, os_error = errno_of(caught.value)  # pyserial's error's __context__
    assert isinstance(os_error, ConnectionRefusedError), caught.value
    found = diagnose(caught.value, url, timeout=0.25)
    assert found.cause == "refused", found
    assert found.message == f"nothing listens at 127.0.0.1:{port} (connection refused)"
    assert "device server" in found.hint
    report = _probe(url, timeout=0.25)  # the device server is connected to first
    assert (report.cause, report.message, report.tried) == ("refused", found.message, [])
