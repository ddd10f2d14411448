"""Faithful to a module we did not build: the drivers, the recorder and replay against an
LDQ-412 written from the datasheet alone (tests/support/independent_module.py: scan 0 1809 µs after
power-on, its clock 150 ppm fast, no filler scans, at most 64 registers a read, answers 1-4
ms late, a power cycle of 1.75 s). Replay must give its recording back exactly: the
finding was every counter shifted by one and device times re-gridded."""

from __future__ import annotations

import time

import pytest

from loopcal.drivers import ldq412
from loopcal.drivers.errors import DAQError
from tests.support.drivers import open_ok
from tests.support.independent_module import IndependentModule
from tests.support.processes import record
from tests.support.recordings import read_scans
from tests.support.replay import assert_same_scans, finish, replay_and_record

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def _wait_made(mod: IndependentModule, n: int = 1, timeout: float = 5.0) -> None:
    """Until the module's scan thread made ``n`` scans; it answers nothing before scan 0
    (a sleep of its 1.8 ms phase assumed the thread ran in time, which load delays)."""
    deadline = time.monotonic() + timeout
    while len(mod.made) < n:
        assert time.monotonic() < deadline, f"{len(mod.made)} of {n} scans in {timeout} s"
        time.sleep(0.001)


def _read_for(daq, seconds: float, out: list, until=lambda: True) -> None:
    """Read every 10 ms for ``seconds``, and then on until ``until()`` (at most 15 s more:
    a loaded machine has held a pseudo-terminal's bytes back for 2.7 s)."""
    t_end = time.monotonic() + seconds
    deadline = t_end + 15.0
    errors: list[str] = []
    while time.monotonic() < t_end or not until():
        # (ci57, ci59: 15 s without a scan of the new power-on over ASCII; the reads'
        # errors, whole in the captured output, and the last scans say what the driver met)
        if time.monotonic() >= deadline:
            print(f"{len(errors)} errors, the last:", *errors[-8:], "last scans:", *out[-3:],
                  sep="\n")  # fmt: skip
        assert time.monotonic() < deadline, "no scan of what was waited for (see the output)"
        try:
            out += daq.read_scans()
        except DAQError as exc:  # a power cycle: the next call reconnects
            errors.append(f"{type(exc).__name__}: {exc}")
        time.sleep(0.01)


@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu", "ascii"])
def test_the_drivers_read_it_exactly(transport):
    with IndependentModule(transport, rate_hz=50) as mod:
        # The first FIFO read finds 20 or more waiting, asks for the datasheet's 20 (120
        # registers), is refused and halves to 10. Read every 10 ms from the start, the
        # first read refused was the first to find 10 or more waiting, at a time a loaded
        # machine decides, and halved whatever it asked (seen: fifo_chunk 8).
        _wait_made(mod, ldq412.FIFO_MAX_SCANS_PER_READ)
        daq = open_ok(mod.url, timeout=0.1)  # the connect is not the subject: retried
        got: list = []
        try:
            _read_for(daq, 0.5, got)
            mod.power_cycle(4.0 if transport == "ascii" else 0.5)
            if transport == "ascii":
                # No poll until the new power-on's counter is past the last one read (ci65:
                # polls failed that long under load): over ASCII, whose restart flag stays
                # set, only the host's clock tells this restart, for a module off longer
                # than sequence.ANSWER_AGE_S
                past = got[-1].counter + 5
                deadline = time.monotonic() + 15.0
                while not any(b == 1 and c > past for b, c, *_ in mod.made[-3:]):
                    assert time.monotonic() < deadline, "the module did not come back"
                    time.sleep(0.01)
            _read_for(daq, 1.0, got, until=lambda: bool(got) and got[-1].epoch == 1)
            time.sleep(0.5)  # 25 scans wait: more than one 64-register read holds
            _read_for(daq, 0.5, got)
        finally:
            daq.close()
        made = {(b, c): (t, codes) for b, c, t, codes, _ in mod.made}
    epochs = [s.epoch for s in got]
    assert epochs[0] == 0 and epochs[-1] == 1 and sorted(epochs) == epochs
    for s in got:
        assert made[(s.epoch, s.counter)] == (s.time_us, s.codes), s
    if transport != "ascii":  # the FIFO: every scan once, in reads of 10 (64 registers)
        # unless the driver gave up on a FIFO read (its answer held past 0.1 s)
        lost = daq.sequencer.fifo_reads_lost
        assert lost or sum(s.missed for s in got if not s.restarted) == 0
        assert daq.fifo_chunk == 10
    assert got[0].time_us == 1809 + got[0].counter * 20_000


def test_its_recording_replays_exactly_on_every_transport(tmp_path):
    with IndependentModule("modbus-tcp", rate_hz=20) as mod:
        _wait_made(mod)
        rec = record(mod.url, tmp_path / "src", "--read-period", "0.1")
        rec.wait_for("recording to", timeout=30)
        time.sleep(1.2)
        mod.power_cycle(1.75)
        rec.wait_for("module restarted", timeout=15)
        time.sleep(1.2)
        rc, _ = rec.stop()
        made = {(b, c): (t, codes) for b, c, t, codes, _ in mod.made}
    assert rc == 0, rec.text
    original = read_scans(tmp_path / "src")
    assert original["restarted"][1:].sum() == 1
    for r in original:  # the recording is the module's own scans
        key = (int(r["epoch"] - original["epoch"][0]), int(r["counter64"]))
        assert made[key] == (int(r["time64_us"]), tuple(int(c) for c in r["codes"]))
    runs = {
        t: replay_and_record(tmp_path / "src", tmp_path / t, t, 1.0 if t == "ascii" else 2.0)
        for t in ("modbus-tcp", "modbus-rtu", "ascii")
    }
    for player, recorder in runs.values():
        finish(player, recorder)
    for t in runs:
        assert_same_scans(original, read_scans(tmp_path / t), polled=t == "ascii")
