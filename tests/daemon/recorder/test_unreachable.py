"""While the module cannot be reached, the recorder says why (what ``loopcal probe`` would
say: the cause and what to do) in its ``disconnect`` event and again every report period,
not once and not at every retry: the acquisition's own loop, and ``loopcal record`` as a
process, against a closed port."""

from __future__ import annotations

import logging
import re
import threading
import time
from pathlib import Path

import pytest

from loopcal.daemon.recorder.acquisition import Acquisition
from tests.support.processes import free_port, record


def test_an_unreachable_module_is_explained_every_report_period_not_every_retry(caplog) -> None:
    """The acquisition's own loop, against a closed port: one line per period, each with
    the cause and the hint, while it retries many times more (every 0.05 s at first)."""
    url = f"modbus-tcp://127.0.0.1:{free_port()}"
    acq = Acquisition(url, lambda batch: None, report_every=0.4)
    stop = threading.Event()
    thread = threading.Thread(target=acq.run, args=(stop,))
    caplog.set_level(logging.WARNING, logger="loopcal.daemon.recorder.acquisition")
    start = time.monotonic()
    thread.start()
    try:
        deadline = start + 30
        while len(_still(caplog)) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        stop.set()
        thread.join(10)
    elapsed = time.monotonic() - start
    lines = _still(caplog)
    assert len(lines) >= 3, caplog.text
    assert len(lines) <= elapsed / 0.4 + 1  # no more than one a period
    assert acq.stats.read_errors > 2 * len(lines)  # the retries are not each said
    for line in lines:
        assert re.search(r"DAQ still unreachable after \d+ s: nothing listens at 127\.0\.0\.1:\d+"
                         r" \(connection refused\) \[refused\]; is the module powered", line)
    first = [r.getMessage() for r in caplog.records if r.getMessage().startswith("disconnect:")]
    assert len(first) == 1 and "why: nothing listens at" in first[0]
    assert acq.diagnosis is not None and acq.diagnosis.cause == "refused"


def _still(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.getMessage().startswith("DAQ still unreachable")]  # fmt: skip


@pytest.mark.slow
def test_loopcal_record_to_a_closed_port_says_why_every_period(tmp_path: Path) -> None:
    port = free_port()
    rec = record(f"modbus-tcp://127.0.0.1:{port}", tmp_path / "rec", "--unreachable-report", "1")
    try:
        first = rec.wait_for(r"disconnect: DAQDisconnected: .*why: nothing listens at "
                             rf"127\.0\.0\.1:{port} \(connection refused\) \[refused\]; ",
                             timeout=60)  # fmt: skip
        seen = first
        for _ in range(3):
            seen = rec.wait_for(rf"WARNING .*DAQ still unreachable after \d+ s: nothing listens "
                                rf"at 127\.0\.0\.1:{port} \(connection refused\) \[refused\]; "
                                "is the module powered", after=seen + 1, timeout=30)  # fmt: skip
    finally:
        rc, _ = rec.stop()
    assert rc == 1, rec.text  # nothing recorded
    said = [line for line in rec.lines if "DAQ still unreachable" in line]
    assert 3 <= len(said) and len(rec.lines) < 40, rec.text  # a line a period, not a retry
