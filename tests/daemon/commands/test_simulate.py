"""`loopcal simulate` as a real subprocess: where it listens, ground truth, signals, faults."""

import json
import signal
import subprocess
import sys
import time
from urllib.parse import urlsplit

import numpy as np
import pytest

from loopcal.drivers import DAQTimeout, open_daq
from tests.support.processes import loopcal_main

CMD = [sys.executable, "-m", "loopcal.daemon.cli", "simulate"]


def start(*args: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(
        [*CMD, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    line = proc.stdout.readline()
    assert line.startswith("listening: "), (line, proc.stderr.read() if proc.poll() else "")
    return proc, line.split(": ", 1)[1].strip()


def read_truth(path):
    lines = [json.loads(s) for s in path.read_text().splitlines()]
    assert lines[0]["type"] == "header"
    return lines[0], [r for r in lines[1:] if r["type"] == "scan"]


@pytest.mark.slow
@pytest.mark.parametrize(("transport", "line"),
                         [("modbus-tcp", "pty"), ("ascii", "pty"), ("modbus-rtu", "tcp")])
def test_scans_read_match_the_ground_truth_file(tmp_path, transport, line):
    out = tmp_path / "truth.jsonl"
    proc, url = start("--transport", transport, "--line", line, "--scan-rate", "50",
                      "--seed", "4", "--truth-out", str(out), "--truth", "d03=101.25")  # fmt: skip
    try:
        assert url.startswith(transport + "://")
        # a serial line behind the device server is reached at its host and port
        assert (urlsplit(url).port is not None) is (transport == "modbus-tcp" or line == "tcp")
        daq = open_daq(url, timeout=1.0)
        scans = []
        deadline = time.monotonic() + 20  # about 1 s at 50 Hz; a loaded machine polls slower
        while len(scans) <= 50:
            assert time.monotonic() < deadline, len(scans)
            scans += daq.read_scans()
            time.sleep(0.005)
        daq.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    header, truth = read_truth(out)
    assert header["parameters"]["d03"] == 101.25
    assert header["scenario"]["name"] == "hand"
    by_counter = {(r["boot"], r["counter"]): r for r in truth}
    assert len(scans) > 50
    for s in scans:
        r = by_counter[(0, s.counter)]
        assert tuple(r["codes"]) == s.codes and r["time_us"] == s.time_us
    assert all(len(r["euler_deg"]) == 3 for r in truth)
    if transport != "ascii":  # the FIFO gives every scan once; the file has them all
        assert [s.counter for s in scans] == list(range(scans[0].counter, scans[-1].counter + 1))


@pytest.mark.slow
def test_scheduled_stall_and_restart_reach_the_driver(tmp_path):
    out = tmp_path / "truth.jsonl"
    # the module's clock starts at the driver's first request, and the stall (2.5 s of
    # wall time at x4) outlasts the driver's timeout five times: a read in it times out,
    # however late a busy machine starts this test's reading (a stall of 0.25 s wall could
    # be over before the first read, and one of 1 s was, once, in a whole run on four
    # workers)
    proc, url = start("--speed", "4", "--wait-for-client", "--fault", "stall@1+10",
                      "--fault", "restart@12", "--duration", "17",
                      "--truth-out", str(out))  # fmt: skip
    daq = open_daq(url, timeout=0.5)
    timeouts = 0
    restarted = []
    deadline = time.monotonic() + 8
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            restarted += [s for s in daq.read_scans() if s.restarted]
        except DAQTimeout:
            timeouts += 1
        except Exception:  # the power cycle drops the TCP connection; the driver reconnects
            pass
        time.sleep(0.02)
    late = daq.late_fifo_answers
    daq.close()
    assert proc.wait(10) == 0
    log = proc.stdout.read()
    assert "fault on: stall" in log and "fault on: restart" in log
    # the stall reached the driver: a read timed out, or a FIFO read (which waits longer,
    # its scans having left the module) was answered after the timeout
    assert timeouts + late >= 1
    assert restarted, "the driver must report the power cycle"
    _, truth = read_truth(out)
    assert {r["boot"] for r in truth} == {0, 1}
    assert np.diff([r["counter"] for r in truth if r["boot"] == 1]).tolist() == [1] * (
        sum(r["boot"] == 1 for r in truth) - 1
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--fault", "explode@1"], "bad fault 'explode@1'"),
        (["--fault", "stall@3"], "needs a duration"),
        (["--fault", "stuck@1+1:9=5"], "channel 1..4"),
        (["--truth", "d09=1"], "bad --truth entry 'd09=1'"),
        (["--speed", "0"], "argument --speed: '0': a speed must be a number above 0"),
        (["--twist-every", "-3"], "--twist-every must be 0 or more moves, got -3"),
    ],
)
def test_bad_options_are_named(args, message):
    refused = loopcal_main("simulate", *args)  # in this process: refused before anything starts
    assert refused.returncode == 2
    assert message in refused.stderr


@pytest.mark.slow
def test_replay_of_a_truth_file(tmp_path):
    rec = tmp_path / "rec.jsonl"
    first, _ = start("--speed", "10", "--duration", "3", "--truth-out", str(rec))
    assert first.wait(20) == 0
    _, recorded = read_truth(rec)
    again = tmp_path / "again.jsonl"
    proc, _ = start("--scenario", "replay", "--replay", str(rec), "--speed", "10",
                    "--duration", "3", "--truth-out", str(again))  # fmt: skip
    assert proc.wait(20) == 0
    _, replayed = read_truth(again)
    n = min(len(recorded), len(replayed))
    assert n > 40
    assert [r["codes"] for r in replayed[:n]] == [r["codes"] for r in recorded[:n]]
