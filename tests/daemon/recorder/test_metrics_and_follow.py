"""The daemon for the people who watch it: Prometheus metrics on a loopback port, and the
controller config followed by itself when a calibration replaces it."""

from __future__ import annotations

import time

import numpy as np
import pytest

from loopcal.daemon.config.controller import load_controller_config, write_initial_config
from loopcal.daemon.recording import read_recordings
from loopcal.simulator.open_points import Latency
from tests.support.emulator import hand_emulator
from tests.support.processes import Proc, free_port, record, scrape, taken_port, value, write_config
from tests.support.sessions import truth_for

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]


def test_record_serves_prometheus_metrics(tmp_path):
    port = free_port()
    t0 = time.time()
    with hand_emulator(speed=4.0) as emu:
        # --timeout 1: the emulated module answers from this busy process, where one answer
        # later than the default 0.1 s was a read error, a disconnect (connected 0) or a
        # late FIFO answer; at ten times that, the zero counts below are the driver's own
        # errors on a healthy module
        rec = record(emu.url, tmp_path / "rec", "--metrics", f"127.0.0.1:{port}",
                     "--timeout", "1")  # fmt: skip
        rec.wait_for("recording to", timeout=20)
        time.sleep(1.5)
        first = scrape(port)
        t_first = time.time()
        time.sleep(1.5)
        m = scrape(port)
        rc, _ = rec.stop()
    assert rc == 0, rec.text
    assert "not only to this machine" not in rec.text  # loopback: nothing exposed
    assert value(m, "loopcal_scans_recorded_total") > value(first, "loopcal_scans_recorded_total")
    assert value(m, "loopcal_scans_recorded_total") > 20
    assert value(m, "loopcal_bytes_written_total") > 1000
    assert value(m, "loopcal_daq_connected") == 1.0
    assert value(m, "loopcal_last_scan_age_seconds") < 2.0
    started = value(first, "loopcal_recorder_start_time_seconds")
    assert t0 <= started <= t_first and value(m, "loopcal_recorder_start_time_seconds") == started
    assert value(m, "loopcal_events_total", kind="connect", level="info") >= 1
    assert value(m, "loopcal_scans_missed_total") == 0 and value(m, "loopcal_disk_error") == 0
    assert value(m, "loopcal_recording_directory_bytes") > 0
    assert {lab["sensor"] for lab, _ in m["loopcal_offset_drift_alarm"]} == {"1", "2", "3", "4"}
    assert value(m, "loopcal_loop_closure_threshold") > 20
    assert value(m, "loopcal_controller_config_info", sha256="") == 1.0  # reference geometry
    # never calibrated: a state of its own, and no age (not a NaN an alert cannot compare)
    assert value(m, "loopcal_controller_config_calibrated") == 0.0
    assert "loopcal_controller_config_calibration_age_seconds" not in m
    assert value(m, "loopcal_daq_read_errors_total") == 0
    assert value(m, "loopcal_daq_late_answers_total") == 0
    with pytest.raises(OSError):  # closed with the recorder
        scrape(port)


def test_a_module_answering_late_costs_no_scan_and_the_metrics_say_so(tmp_path):
    """A third of the answers 150-400 ms late, beyond the datasheet's 100-ms timeout: the
    snapshots given up on are retried, the FIFO reads waited for, and every scan is kept."""
    port = free_port()
    with hand_emulator(speed=4.0) as emu:
        rec = record(emu.url, tmp_path / "rec", "--metrics", f"127.0.0.1:{port}")
        rec.wait_for("recording to", timeout=20)
        emu.faults.latency(Latency(slow_fraction=0.3, slow_ms=(150.0, 400.0)))
        time.sleep(6.0)
        m = scrape(port)
        rc, _ = rec.stop()
    assert rc == 0, rec.text
    c = read_recordings(tmp_path / "rec").scans["counter64"].astype(np.int64)
    assert len(c) > 6.0 * 20 * 4.0 * 0.8
    assert np.all(np.diff(c) == 1) and value(m, "loopcal_scans_missed_total") == 0
    assert value(m, "loopcal_daq_late_answers_total") > 0
    assert value(m, "loopcal_daq_read_errors_total") > 0  # the late snapshots


def test_a_taken_or_bad_metrics_address_is_refused(tmp_path):
    with taken_port() as port:
        proc = record("modbus-tcp://127.0.0.1:1", tmp_path / "r", "--metrics",
                      f"127.0.0.1:{port}", "--duration", "1")  # fmt: skip
        assert proc.wait(30) == 2 and "--metrics" in proc.text and "in use" in proc.text
    proc = record("modbus-tcp://127.0.0.1:1", tmp_path / "r", "--metrics", "9464")
    assert proc.wait(30) == 2 and "HOST:PORT" in proc.text


def test_the_daemon_follows_a_replaced_controller_config(tmp_path):
    controller_dir = tmp_path / "controller"
    controller_dir.mkdir()
    config = write_initial_config(controller_dir / "controller.toml")
    port = free_port()
    with hand_emulator(speed=4.0) as emu:
        cfg = write_config(tmp_path / "daemon.toml", emu.url, tmp_path / "rec",
                           f'\n[controller]\nconfig = "{config}"\n\n[metrics]\n'
                           f'listen = "127.0.0.1:{port}"\n')  # fmt: skip
        daemon = Proc(["daemon", "--config", str(cfg)])
        daemon.wait_for("recording to", timeout=20)
        old_sha = load_controller_config(config).sha256
        write_initial_config(config, force=True, params=truth_for(2))  # a calibration wrote it
        new_sha = load_controller_config(config).sha256
        i = daemon.wait_for("was replaced", timeout=15)
        m = scrape(port)
        config.write_text("[parameters]\nA1x = 'broken'\n")  # a bad edit: refused, old kept
        daemon.wait_for("changed but does not load", timeout=15, after=i)
        time.sleep(1.5)
        rc, _ = daemon.stop()
    assert rc == 0, daemon.text
    assert value(m, "loopcal_controller_config_info", sha256=new_sha) == 1.0
    out = read_recordings(tmp_path / "rec")
    reloads = out.events_of("config_reload")
    assert [e.details["ok"] for e in reloads] == [True, False]
    assert reloads[0].details["controller_sha256"] == new_sha != old_sha
    shas = [f.metadata["controller_config"]["sha256"] for f in out.files]
    assert shas[0] == old_sha and shas[-1] == new_sha  # a new file from the change on


def test_metrics_on_every_interface_warn_and_answer_200_scrapes_at_once(tmp_path):
    """``--metrics 0:PORT`` binds every interface: served, with a warning naming that; and
    200 scrapers at once are all answered (the socketserver backlog of 5 timed out 16 of
    600). The scrapes go to 127.0.0.1 only."""
    from concurrent.futures import ThreadPoolExecutor

    port = free_port()
    with hand_emulator(speed=4.0) as emu:
        rec = record(emu.url, tmp_path / "rec", "--metrics", f"0:{port}")
        try:
            rec.wait_for("recording to", timeout=20)
            line = rec.lines[rec.wait_for("not only to this machine", timeout=5)]
            assert f"metrics on 0:{port} are served to every interface" in line, line

            def one(_: int) -> float:
                # answered, with the gauge; a busy machine may see the emulated module
                # slow for a read (0), which is not what this test is about
                return value(scrape(port), "loopcal_daq_connected")

            with ThreadPoolExecutor(200) as pool:
                answered = list(pool.map(one, range(200)))
            rc, _ = rec.stop()
        finally:
            rec.kill()
    assert rc == 0, rec.text
    assert len(answered) == 200 and set(answered) <= {0.0, 1.0} and 1.0 in answered
