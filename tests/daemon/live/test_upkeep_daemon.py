"""The daemon's upkeep end to end: ``loopcal daemon`` reading an emulated module on a robot
at work (a task loop, the emulator's clock five times wall time), a sensor swapped or not:
it proposes once, and writes once in write mode and then watches the new values. The
upkeep's segments are of the scans' stamps, which are the host's time: a faster emulated
clock would put more scans in each (and cost more CPU), not make them come sooner. So the
daemon tests 5-s segments (``[upkeep].segment``; 500 scans each at this speed), which see
the change sooner than the default 15 s (tests/daemon/live/test_upkeep.py).

That an unchanged robot gets nothing is shown in-process over 120 segments
(tests/daemon/live/test_upkeep.py): a change must stand two segments before anything is
fitted, so a daemon run as short as these could write nothing whatever the upkeep did."""

from __future__ import annotations

import itertools
import json
import os
import signal
import time

import pytest

from loopcal.calibration.parameters import INDEX, NOMINAL
from loopcal.daemon.config.controller import load_controller_config, write_initial_config
from loopcal.daemon.live.upkeep_state import load_record, state_path
from loopcal.daemon.recording import read_recordings
from loopcal.daemon.worker.proposal import proposal_path, read_proposal
from loopcal.simulator.drift import OffsetDrift
from loopcal.simulator.phases import Phases
from loopcal.simulator.scenarios import HandMoves
from loopcal.simulator.task import TaskLoop
from tests.support.emulator import hand_emulator
from tests.support.processes import NotifySocket, Proc, free_port, loopcal, scrape, write_config

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]
_STARTS = itertools.count()


def start(tmp_path, emu, mode: str | None = None, extra: str = "") -> tuple[Proc, NotifySocket]:
    controller = tmp_path / "controller.toml"
    upkeep = "\n[upkeep]\nsegment = 5\n" + ("" if mode is None else f'mode = "{mode}"\n')
    cfg = write_config(tmp_path / "daemon.toml", emu.url, tmp_path / "rec",
                       f'\n[controller]\nconfig = "{controller}"\n{upkeep}{extra}')  # fmt: skip
    notify = NotifySocket(tmp_path / f"n{next(_STARTS)}.sock")  # one per start
    return Proc(["daemon", "--config", str(cfg)], env={"NOTIFY_SOCKET": str(notify.path)}), notify


def test_the_daemon_proposes_a_swapped_sensor_once(tmp_path):
    config = write_initial_config(tmp_path / "controller.toml")  # the emulator's geometry
    before = config.read_bytes()
    swap = (OffsetDrift("step", 3, 45.0, 0.8),)
    port = free_port()
    with hand_emulator(speed=5.0, seed=3, drifts=swap, motion=TaskLoop(3)) as emu:
        daemon, notify = start(tmp_path, emu, extra=f'\n[metrics]\nlisten = "127.0.0.1:{port}"\n')
        try:
            line = daemon.lines[daemon.wait_for("recalibration_proposed", timeout=120)]
            assert "d03" in line and "every gate passed" in line
            deadline = time.monotonic() + 15
            while "RECALIBRATION PROPOSED (d03)" not in notify.wait_for("STATUS",
                                                                        timeout=10)["STATUS"]:
                assert time.monotonic() < deadline, notify.messages[-3:]
            status = loopcal("upkeep", "status", "--config", tmp_path / "daemon.toml", "--json")
            m = scrape(port)
            assert m["loopcal_upkeep_proposal_pending"][0][1] == 1.0
            assert m["loopcal_upkeep_proposal_age_seconds"][0][1] >= 0
            assert m["loopcal_upkeep_fits_total"][0][1] >= 3
            assert m["loopcal_upkeep_fit_cpu_seconds_total"][0][1] > 0
            time.sleep(6)  # half a minute more of the robot's motion: nothing new
            last = scrape(port)
            rc, _ = daemon.stop(30)
        finally:
            daemon.kill()
    assert rc == 0, daemon.text
    assert config.read_bytes() == before  # propose: the config in force untouched
    p = read_proposal(load_controller_config(config))
    assert p is not None and list(p.values) == ["d03"]
    assert abs(p.values["d03"] - (NOMINAL[INDEX["d03"]] + 0.8)) <= 0.05
    doc = json.loads(status.stdout)
    assert status.returncode == 0 and doc["pending"] and doc["values"] == p.values
    rec = read_recordings(tmp_path / "rec")
    events = rec.events_of("recalibration_proposed")
    assert len(events) == 1 and events[0].details["path"] == str(proposal_path(config))
    assert events[0].details["since_ns"] >= 0
    # the metrics count what the recording holds (nothing can happen between the last
    # scrape and the stop: the proposal stands, and a minute showed nothing new)
    for metric, kind in (("proposals", "recalibration_proposed"),
                         ("withdrawals", "recalibration_withdrawn"),
                         ("writes", "recalibrated"), ("refusals", "recalibration_refused")):
        assert last[f"loopcal_upkeep_{metric}_total"][0][1] == len(rec.events_of(kind)), metric


def test_write_mode_rewrites_the_config_once_and_the_daemon_follows_it(tmp_path):
    config = write_initial_config(tmp_path / "controller.toml")
    swap = (OffsetDrift("step", 1, 45.0, -0.6),)
    with hand_emulator(speed=5.0, seed=4, drifts=swap, motion=TaskLoop(4)) as emu:
        daemon, _ = start(tmp_path, emu, "write")
        try:
            daemon.wait_for(r"recalibrated: upkeep: wrote d01", timeout=120)
            daemon.wait_for(r"config_reload: .*was replaced", timeout=30)
            time.sleep(9)  # 45 s more of the robot's motion, watched at the new values
            rc, _ = daemon.stop(30)
        finally:
            daemon.kill()
    assert rc == 0, daemon.text
    assert daemon.text.count("recalibrated: upkeep") == 1, daemon.text
    new = load_controller_config(config)
    assert abs(new.params[INDEX["d01"]] - (NOMINAL[INDEX["d01"]] - 0.6)) <= 0.05
    assert new.provenance["upkeep"]["mode"] == "write"
    assert len(list(tmp_path.glob("controller.toml.*.prev"))) == 1
    assert not os.path.lexists(proposal_path(config))


def _change_at(rec, device_s: float) -> int:
    """The host stamp of the first scan at or after device time ``device_s``, ns."""
    scans = rec.scans
    return int(scans["stamp_ns"][scans["time64_us"] >= device_s * 1e6][0])


def test_an_unattributable_change_is_said_kept_through_a_sigkill_and_fixed_by_the_hand(tmp_path):
    """Sensor 4 moves while the task loop cannot tell it from sensor 3: said within 30 s,
    naming both; the daemon SIGKILLed and started again says it at once; the hand that
    comes later tells them apart, and d04 alone is written."""
    config = write_initial_config(tmp_path / "controller.toml")
    life = Phases([(0.0, TaskLoop(1, waypoints=2)), (250.0, HandMoves(1))])
    swap_at = 75.0  # device s: 15 s of host time at five times
    port = free_port()
    metrics = f'\n[metrics]\nlisten = "127.0.0.1:{port}"\n'
    with hand_emulator(speed=5.0, seed=1, motion=life,
                       drifts=(OffsetDrift("step", 4, swap_at, -0.6),)) as emu:
        daemon, _ = start(tmp_path, emu, "write", extra=metrics)
        try:
            line = daemon.lines[daemon.wait_for("offset_change: upkeep", timeout=90)]
            assert "cannot tell which offset moved" in line and "d03" in line and "d04" in line
            daemon.signal(signal.SIGKILL)
            daemon.wait(10)
        finally:
            daemon.kill()
        again, notify = start(tmp_path, emu, "write", extra=metrics)
        try:
            status = notify.wait_for("STATUS", timeout=30)["STATUS"]
            assert "LOOPS OPEN" in status and "d04" in status, status  # before any segment
            again.wait_for("offset_change: upkeep", timeout=10)  # said at once, in this run
            m = scrape(port)
            assert m["loopcal_upkeep_change_unattributed"][0][1] == 1.0
            st = loopcal("upkeep", "status", "--config", tmp_path / "daemon.toml", "--json")
            record = json.loads(st.stdout)["record"]
            assert record["change"] is not None and record["change"]["names"] == []
            again.wait_for(r"recalibrated: upkeep: wrote d04", timeout=120)
            rc, _ = again.stop(30)
        finally:
            again.kill()
    assert rc == 0, again.text
    new = load_controller_config(config)
    assert abs(new.params[INDEX["d04"]] - (NOMINAL[INDEX["d04"]] - 0.6)) <= 0.05
    assert all(new.params[INDEX[n]] == NOMINAL[INDEX[n]] for n in INDEX if n != "d04")
    rec = read_recordings(tmp_path / "rec")
    said = rec.events_of("offset_change")
    assert said[0].stamp_ns - _change_at(rec, swap_at) <= 30e9, said[0]
    written = rec.events_of("recalibrated")
    assert len(written) == 1 and written[0].stamp_ns > _change_at(rec, 250.0)


def test_a_swap_while_the_daemon_is_stopped_is_written_within_a_minute_of_the_restart(tmp_path):
    config = write_initial_config(tmp_path / "controller.toml")
    swap_at = 150.0  # device s: while the daemon is stopped
    with hand_emulator(speed=5.0, seed=2, motion=TaskLoop(2),
                       drifts=(OffsetDrift("step", 2, swap_at, 0.7),)) as emu:
        daemon, _ = start(tmp_path, emu, "write")
        try:
            daemon.wait_for(r"loopcal_upkeep|scans written|recording ", timeout=30)
            kept = state_path(tmp_path / "rec")
            deadline = time.monotonic() + 60
            while not kept.exists() or load_record(kept).baseline.segments < 3:
                assert time.monotonic() < deadline, daemon.text  # its baseline kept
                time.sleep(0.2)
            rc, _ = daemon.stop(30)
        finally:
            daemon.kill()
        assert rc == 0, daemon.text
        while emu.clock.now_ns() < (swap_at + 10) * 1e9:  # the swap, the daemon stopped
            time.sleep(0.2)
        again, _ = start(tmp_path, emu, "write")
        t0 = time.monotonic()
        try:
            again.wait_for(r"recalibrated: upkeep: wrote d02", timeout=60)
            took = time.monotonic() - t0
            rc, _ = again.stop(30)
        finally:
            again.kill()
    assert rc == 0 and took <= 60, (took, again.text)
    new = load_controller_config(config)
    assert abs(new.params[INDEX["d02"]] - (NOMINAL[INDEX["d02"]] + 0.7)) <= 0.05
