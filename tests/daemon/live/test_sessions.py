"""A technician's session through the running daemon: the control socket (its protocol,
fuzzed while the daemon records), one session at a time, a client that vanishes, a daemon
that stops, and ``loopcal session`` end to end against a daemon subprocess."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from loopcal.calibration.parameters import INDEX, NAMES
from loopcal.daemon.config.controller import load_controller_config
from loopcal.daemon.live.control import (
    MAX_MESSAGE_BYTES,
    ControlClient,
    ControlError,
    ProtocolError,
    parse_request,
)
from loopcal.daemon.live.sessions import ControlServer
from loopcal.daemon.recorder.engine import Recorder
from loopcal.daemon.recorder.settings import RecorderSettings
from loopcal.daemon.recording import read_recordings
from tests.support.emulator import hand_emulator
from tests.support.fuzz import examples
from tests.support.js import watch_live
from tests.support.processes import (
    Proc,
    free_port,
    fresh_config,
    listening_url,
    loopcal,
    loopcal_main,
)
from tests.support.sessions import PAUSE_S, truth_for

pytestmark = pytest.mark.timeout(180)


# ---------------------------------------------------------------------------- protocol


@pytest.mark.slow
@settings(max_examples=examples(500), deadline=None)
@given(st.one_of(
    st.binary(max_size=300),
    st.dictionaries(st.text(max_size=12), st.recursive(
        st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=40),
        lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=5), c, max_size=3),
        max_leaves=8), max_size=6).map(lambda d: json.dumps(d).encode()),
    st.fixed_dictionaries({"request": st.sampled_from(["start", "stop", "status", "stream"])},
                          optional={"note": st.text(max_size=600), "target_mm": st.floats(),
                                    "duration_s": st.none() | st.floats(),
                                    "until_enough": st.booleans() | st.integers(),
                                    "free": st.none() | st.text(max_size=20),
                                    "x": st.integers()}).map(lambda d: json.dumps(d).encode()),
))  # fmt: skip
def test_any_line_is_a_request_or_a_protocol_error_naming_the_problem(line):
    try:
        name, start = parse_request(line)
    except ProtocolError as exc:
        assert str(exc)
        return
    assert name in ("start", "stop", "status", "stream")
    if start is not None:
        assert 0 < start.target_mm <= 10 and len(start.note) <= 500
        assert start.duration_s is None or 0 < start.duration_s <= 4 * 3600


def test_requests_that_would_reach_beyond_a_session_are_refused():
    for line, why in [
        (b'{"request": "reload"}', "unknown request 'reload'"),
        (b'{"request": "start", "config": "/etc/passwd"}', "unknown field"),
        (b'{"request": "start", "note": "a\\nb"}', "control characters"),
        (b'{"request": "start", "target_mm": NaN}', "not JSON"),
        (b'{"request": "start", "duration_s": 1e9}', "duration_s must be"),
        (b"[1, 2]", "not a JSON object"),
        (b"\xff\xfe", "not UTF-8"),
        (b"x" * (MAX_MESSAGE_BYTES + 1), "more than"),
    ]:
        with pytest.raises(ProtocolError, match=why):
            parse_request(line)


# ---------------------------------------------------------------------------- in process


class Daemon:
    """A recorder with its control server, in this process, on an emulated module (four
    times as fast as a real one: its FIFO holds 3.2 s, far more than a busy machine's
    stalls, so that the tests can ask that no scan be lost)."""

    def __init__(self, tmp_path: Path, runtime: Path, *, speed: float = 4.0,
                 client_timeout: float = 30.0) -> None:  # fmt: skip
        self.emu = hand_emulator(speed=speed, seed=4)
        self.emu.start()
        config = fresh_config(tmp_path / "controller.toml")
        self.settings = RecorderSettings(
            daq_url=self.emu.url, directory=tmp_path / "rec", controller_config=config,
            read_period_s=0.05, flush_period_s=0.2, health=False,
            control_socket=runtime / "control.sock").checked()  # fmt: skip
        self.recorder = Recorder(self.settings, command="test daemon", service=True)
        self.control = ControlServer(self.recorder, runtime / "control.sock",
                                     client_timeout=client_timeout)  # fmt: skip
        self.recorder.stop_listeners.append(self.control.stop_session)
        self.thread = threading.Thread(target=self.recorder.run, daemon=True)
        self.thread.start()

    def client(self) -> ControlClient:
        return ControlClient(self.settings.control_socket)

    def wait_scans(self, n: int, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while self.recorder.status.scans_written < n:
            assert time.monotonic() < deadline, "the recorder wrote no scans"
            time.sleep(0.05)

    def stop(self) -> np.ndarray:
        """Stop; the recording's rows (every scan of the module, or the test fails)."""
        self.recorder.request_stop("test over")
        self.thread.join(30)
        self.control.close()
        self.emu.close()
        return read_recordings(self.settings.directory)


@pytest.fixture
def daemon(tmp_path, runtime_directory):
    d = Daemon(tmp_path, runtime_directory)
    yield d
    if d.thread.is_alive():
        d.stop()


def expect(client: ControlClient, kind: str, timeout: float = 30.0) -> dict:
    """The next message of ``kind`` (guidance and status messages before it skipped)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = client.receive(timeout=0.5)
        if msg is not None and msg["type"] == kind:
            return msg
        if msg is not None and msg["type"] == "error" and kind != "error":
            raise AssertionError(msg)
    raise AssertionError(f"no {kind} within {timeout} s")


def no_scan_lost(out) -> None:
    """Every scan the module made since the first recorded is in the recording (the
    events that say otherwise are shown)."""
    rows = out.scans
    why = [e.message for e in out.events if e.kind in ("gap", "overflow", "foreign_reader")]
    assert len(rows) and int(rows["missed"].sum()) == 0, why
    assert np.all(np.diff(rows["counter64"].astype(np.int64)) == 1), why


@pytest.mark.slow
def test_hostile_clients_never_cost_the_recording_a_scan(daemon):
    daemon.wait_scans(20)
    # a client that sends much and reads nothing, one that sends a huge line, many idle
    # ones, garbage of every kind (hypothesis), and then a well-behaved client is served
    stuffer = socket.socket(socket.AF_UNIX)
    stuffer.connect(str(daemon.settings.control_socket))
    stuffer.setblocking(False)
    try:
        for _ in range(2000):
            stuffer.send(b'{"request": "status"}\n')
    except BlockingIOError:
        pass  # its buffers are full: the daemon stopped reading it, not recording
    huge = socket.socket(socket.AF_UNIX)
    huge.connect(str(daemon.settings.control_socket))
    huge.sendall(b"x" * (MAX_MESSAGE_BYTES + 10))
    assert b"more than" in huge.recv(4096)
    idle = []
    for _ in range(20):  # more than the server serves: the last are told and closed
        s = socket.socket(socket.AF_UNIX)
        s.connect(str(daemon.settings.control_socket))
        idle.append(s)

    @settings(max_examples=examples(150), deadline=None,
              suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
    @given(st.lists(st.binary(min_size=1, max_size=200), min_size=1, max_size=5))
    def garbage(lines):
        with socket.socket(socket.AF_UNIX) as s:
            s.settimeout(5)
            try:
                s.connect(str(daemon.settings.control_socket))
            except BlockingIOError:  # the kernel's queue is full: turned away, as it may be
                turned_away.append(lines)
                return
            s.sendall(b"\n".join(lines) + b"\n")
            s.shutdown(socket.SHUT_WR)
            while s.recv(65536):
                pass

    turned_away: list = []
    for s in idle:
        s.close()
    garbage()
    assert len(turned_away) < 150, "every garbage client turned away: none was served"
    with daemon.client() as c:
        c.send("status")
        status = expect(c, "status", 10)
        assert status["session"] is None and "scans written" in status["recorder"]
    stuffer.close()
    huge.close()
    before = daemon.recorder.status.scans_written
    daemon.wait_scans(before + 40)
    no_scan_lost(daemon.stop())


@pytest.mark.slow
def test_one_session_at_a_time_its_owner_stops_it_and_its_window_is_exact(daemon):
    daemon.wait_scans(20)
    with daemon.client() as owner, daemon.client() as other:
        assert daemon.control.session_words() == ""  # the upkeep may act
        owner.send("start", note="sensor 3 replaced", target_mm=0.1)
        started = expect(owner, "started")["session"]
        assert started["note"] == "sensor 3 replaced"
        assert "a technician's session runs" in daemon.control.session_words()  # it holds
        assert started["asked_by"]["pid"] == os.getpid()
        other.send("start")
        refused = expect(other, "error")["error"]
        assert f"a session runs: session {started['id']}" in refused and "sensor 3" in refused
        other.send("stop")
        assert "only the client that started it" in expect(other, "error")["error"]
        other.send("stream")
        expect(other, "streaming")
        update = expect(owner, "guidance")
        assert update["update"]["scans"] > 0 and update["lines"][0].startswith("loopcal")
        expect(other, "guidance")
        owner.send("stop")
        ended = expect(owner, "ended")["session"]
        assert expect(other, "ended")["session"] == ended
    assert ended["reason"] == "stopped" and ended["flushed"] is True and ended["scans"] > 0
    # and a while after: the session's client calibrates and writes now
    assert "session just ended" in daemon.control.session_words()
    out = daemon.stop()
    no_scan_lost(out)
    stamps = out.scans["stamp_ns"]
    inside = (stamps >= ended["since_ns"]) & (stamps <= ended["until_ns"])
    assert inside.sum() == ended["scans"]  # the window is the session's scans, each once
    [start] = out.events_of("session_start")
    [end] = out.events_of("session_end")
    assert start.details["note"] == "sensor 3 replaced" and start.details["session"] == ended["id"]
    assert end.details["reason"] == "stopped" and end.details["since_ns"] == ended["since_ns"]


@pytest.mark.slow
def test_a_session_lasts_its_duration_of_the_modules_scans(daemon):
    daemon.wait_scans(20)
    with daemon.client() as c:
        c.send("start", duration_s=5)
        expect(c, "started")
        ended = expect(c, "ended")["session"]
    assert ended["reason"] == "duration" and ended["scans"] == 5 * 20
    assert ended["last"]["counter64"] - ended["first"]["counter64"] == 99


@pytest.mark.slow
def test_a_vanished_client_abandons_its_session(tmp_path, runtime_directory):
    d = Daemon(tmp_path, runtime_directory, client_timeout=1.5)
    try:
        d.wait_scans(20)
        idle = socket.socket(socket.AF_UNIX)  # connected, and never a word
        idle.connect(str(d.settings.control_socket))
        c = d.client()
        c.send("start", note="closed laptop")
        expect(c, "started")
        # silent (a closed laptop): abandoned after the timeout, the connection still open
        t0 = time.monotonic()
        while d.control.session is not None and time.monotonic() - t0 < 30:
            time.sleep(0.05)
        assert d.control.session is None
        idle.settimeout(10)
        assert idle.recv(1) == b""  # closed for its silence: its place is free again
        idle.close()
        c.close()
        c2 = d.client()
        c2.send("start", note="dropped ssh")
        expect(c2, "started")
        c2.close()  # its process gone: abandoned at once
        t0 = time.monotonic()
        while d.control.session is not None and time.monotonic() - t0 < 30:
            time.sleep(0.05)
    finally:
        out = d.stop()
    ends = out.events_of("session_end")
    assert [e.details["reason"] for e in ends] == ["abandoned", "abandoned"]
    assert "nothing heard from its client for 1.5 s" in ends[0].message
    assert "closed the connection" in ends[1].message
    assert ends[0].level.name == "WARNING"
    no_scan_lost(out)


@pytest.mark.slow
def test_a_daemon_that_stops_ends_the_session_and_writes_its_scans(daemon):
    daemon.wait_scans(20)
    c = daemon.client()
    c.send("start")
    expect(c, "started")
    expect(c, "guidance")
    out = daemon.stop()
    ended = expect(c, "ended", 10)["session"]
    c.close()
    assert ended["reason"] == "daemon stopping" and ended["flushed"] is True
    assert out.events_of("session_end")[0].details["reason"] == "daemon stopping"
    stamps = out.scans["stamp_ns"]
    assert stamps[-1] >= ended["until_ns"]  # every scan of the window was written
    no_scan_lost(out)


# ---------------------------------------------------------------------------- end to end


@pytest.mark.slow
def test_no_daemon_says_so_and_how_to_record_without_one(tmp_path, runtime_directory):
    config = fresh_config(tmp_path / "controller.toml")
    cfg = tmp_path / "daemon.toml"
    cfg.write_text(f'[daq]\nurl = "modbus-tcp://127.0.0.1:1"\n[recording]\ndirectory = '
                   f'"{tmp_path / "rec"}"\n[controller]\nconfig = "{config}"\n')  # fmt: skip
    proc = loopcal("session", "--config", cfg, "--until-enough")
    assert proc.returncode == 2
    assert f"no loopcal daemon answers at {runtime_directory / 'control.sock'}" in proc.stderr
    assert "loopcal record --daq URL" in proc.stderr and "Traceback" not in proc.stderr
    with pytest.raises(ControlError, match="no loopcal daemon"):
        ControlClient(runtime_directory / "control.sock")


@pytest.mark.slow
def test_a_session_through_the_daemon_writes_a_config_that_the_daemon_follows(tmp_path):
    seed = 7
    truth = truth_for(seed)
    every = ",".join(f"{n}={float(truth[i])!r}" for i, n in enumerate(NAMES))
    config = fresh_config(tmp_path / "controller.toml")
    # four times as fast as a real module: the FIFO holds 3.2 s (a busy machine's stalls)
    sim = Proc(["simulate", "--seed", str(seed), "--speed", "4", "--wait-for-client",
                "--twist-every", "2", "--pause", f"{PAUSE_S[0]},{PAUSE_S[1]}",
                "--truth", every])  # fmt: skip
    daemon = None
    try:
        url = listening_url(sim)
        cfg = tmp_path / "daemon.toml"
        cfg.write_text(f'[daq]\nurl = "{url}"\nread_period = 0.05\n[recording]\n'
                       f'directory = "{tmp_path / "rec"}"\n[controller]\n'
                       f'config = "{config}"\n')  # fmt: skip
        daemon = Proc(["daemon", "--config", str(cfg)])
        daemon.wait_for("recording to ")
        # the technician's own recorder is refused while the daemon holds the module
        mine = loopcal("record", "--daq", url, "--out", tmp_path / "mine", "--until-enough")
        assert mine.returncode == 2 and f"(pid {daemon.pid}" in mine.stderr
        assert "loopcal session" in mine.stderr
        session = Proc(["session", "--config", str(cfg), "--until-enough", "--write",
                        "--json", "--note", "sensor 3 replaced"])  # fmt: skip
        rc = session.wait(150)
        assert rc == 0, session.text + "\n" + daemon.text
        docs = [json.loads(line) for line in session.lines if line.startswith("{")]
        *updates, result = docs
        assert updates and updates[-1]["enough"] is True
        assert result["accepted"] is True and result["written"] is True
        assert result["session"]["reason"] == "enough"
        assert result["session"]["note"] == "sensor 3 replaced"
        written = load_controller_config(config)
        for name, p in result["parameters"].items():
            value = written.params[INDEX[name]]
            assert value == pytest.approx(p["value"])
            assert abs(value - truth[INDEX[name]]) <= 3 * p["std"], name
        # the daemon follows the config written
        daemon.wait_for(r"config_reload: the controller config .* was replaced", 30)
        # SIGTERM: 2 s on a quiet machine; a loaded one's fsyncs and joins take longer, and
        # how long is not what this test is about
        rc, _ = daemon.stop(60)
        assert rc == 0
        daemon_text = daemon.text
        daemon = None
    finally:
        if daemon is not None:
            daemon.kill()
        sim.kill()
    out = read_recordings(tmp_path / "rec")
    no_scan_lost(out)  # the daemon's recording missed no scan, session or not
    [end] = out.events_of("session_end")
    assert end.details["reason"] == "enough" and end.details["enough"] is True
    s = result["session"]
    inside = (out.scans["stamp_ns"] >= s["since_ns"]) & (out.scans["stamp_ns"] <= s["until_ns"])
    assert inside.sum() == s["scans"]
    assert "session_start" in daemon_text


@pytest.mark.slow
def test_session_refuses_bad_input_before_asking_the_daemon(tmp_path):
    config = fresh_config(tmp_path / "controller.toml")
    cfg = tmp_path / "daemon.toml"
    cfg.write_text(f'[daq]\nurl = "modbus-tcp://127.0.0.1:1"\n[recording]\ndirectory = '
                   f'"{tmp_path / "rec"}"\n[controller]\nconfig = "{config}"\n')  # fmt: skip
    bare = tmp_path / "bare.toml"
    bare.write_text(f'[daq]\nurl = "modbus-tcp://127.0.0.1:1"\n[recording]\ndirectory = '
                    f'"{tmp_path / "rec"}"\n')  # fmt: skip
    for argv, why in [
        (["--config", cfg, "--target-mm", "0"], "--target-mm: '0': a target must be more than 0"),
        (["--config", cfg, "--note", "a\nb"], "--note: control characters"),
        (["--config", cfg, "--free", "d09"], "--free:"),
        (["--config", cfg, "--duration", "soon"], "'soon' is not a duration"),
        (["--config", bare], "no \\[controller\\].config"),
        (["--config", tmp_path / "missing.toml"], "cannot read the config"),
    ]:
        proc = loopcal_main("session", *argv)
        assert proc.returncode == 2, (argv, proc.stderr)
        assert proc.stderr.startswith("loopcal session: error:") or "usage:" in proc.stderr
        assert re.search(why, proc.stderr), (argv, proc.stderr)


@pytest.mark.slow
def test_the_live_view_shows_a_sessions_guidance(tmp_path, runtime_directory):
    """With [live] on, a technician's session is watched in Foxglove as record's is: its
    guidance on /loopcal/guidance, decoded by the protocol's own client."""
    port = free_port()
    config = fresh_config(tmp_path / "controller.toml")
    with hand_emulator(speed=4.0) as emu:
        cfg = tmp_path / "daemon.toml"
        cfg.write_text(f'[daq]\nurl = "{emu.url}"\nread_period = 0.05\n[recording]\n'
                       f'directory = "{tmp_path / "rec"}"\n[controller]\nconfig = "{config}"\n'
                       f'[live]\nlisten = "127.0.0.1:{port}"\n')  # fmt: skip
        daemon = Proc(["daemon", "--config", str(cfg)])
        try:
            daemon.wait_for("recording to ", 30)
            with ControlClient(runtime_directory / "control.sock") as c:
                c.send("start", note="watched")
                expect(c, "started")
                seen = watch_live(port, 5.0)
                c.send("stop")
                ended = expect(c, "ended")["session"]
            rc, _ = daemon.stop()
        finally:
            daemon.kill()
    assert rc == 0 and ended["reason"] == "stopped"
    guidance = seen["topics"]["/loopcal/guidance"]
    assert guidance["received"] >= 2 and guidance["decoded"] == guidance["received"]
    assert guidance["last"]["scans"] > 0 and guidance["last"]["instruction"]


@pytest.mark.slow
def test_ctrl_c_ends_the_session_and_calibrates_what_it_recorded(daemon, tmp_path):
    daemon.wait_scans(20)
    s = daemon.settings
    cfg = tmp_path / "daemon.toml"
    cfg.write_text(f'[daq]\nurl = "{s.daq_url}"\n[recording]\ndirectory = "{s.directory}"\n'
                   f'[controller]\nconfig = "{s.controller_config}"\n[control]\n'
                   f'socket = "{s.control_socket}"\n')  # fmt: skip
    session = Proc(["session", "--config", str(cfg), "--note", "interrupted"])
    session.wait_for(r"^loopcal guidance ", 60)
    session.signal(signal.SIGINT)
    rc = session.wait(120)
    assert rc in (0, 1), session.text  # the gates decide on what was recorded
    assert "stopping the session" in session.text
    assert re.search(r"session \S+ ended: stopped; [\d,]+ scans", session.text), session.text
    assert "Acceptance gates:" in session.text and "Traceback" not in session.text
    out = daemon.stop()
    [end] = out.events_of("session_end")
    assert end.details["reason"] == "stopped"
    no_scan_lost(out)
