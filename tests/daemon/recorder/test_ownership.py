"""One owner of a module on this host: a second loopcal process that opens a module already
recorded is refused at once, naming the holder; a crashed holder leaves nothing locked; a
serial port is opened exclusively, against programs that are not loopcal too."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from loopcal.daemon.recorder.ownership import (
    Holder,
    ModuleHeld,
    ModuleLock,
    lock_path,
    module_key,
)
from loopcal.drivers import DAQDisconnected, open_daq
from tests.support.fuzz import examples
from tests.support.processes import Proc, listening_url, loopcal, record, write_config

pytestmark = pytest.mark.timeout(60)


# ---------------------------------------------------------------------------- the key


def test_urls_of_one_module_share_a_key_and_others_do_not(tmp_path):
    same = ["modbus-tcp://127.0.0.1:5020", "modbus-tcp://localhost:5020?unit=1",
            "modbus-tcp://[::1]:5020?unit=1&fifo=0", "MODBUS-TCP://LOCALHOST:5020"]  # fmt: skip
    assert len({module_key(u) for u in same}) == 1
    others = ["modbus-tcp://127.0.0.1:5021", "modbus-tcp://127.0.0.1:5020?unit=2",
              "modbus-tcp://10.1.2.3:5020", "modbus-rtu:///dev/ttyUSB0"]  # fmt: skip
    assert len({module_key(u) for u in [same[0], *others]}) == 5
    assert module_key("modbus-tcp://10.1.2.3") == module_key("modbus-tcp://10.1.2.3:502?unit=1")
    # a serial port is one process's, whatever the unit or protocol; symlinks resolved
    device = tmp_path / "ttyUSB7"
    device.touch()
    (tmp_path / "by-id").symlink_to(device)
    keys = {module_key(f"modbus-rtu://{device}?unit=1"), module_key(f"modbus-rtu://{device}?unit=9"),
            module_key(f"ascii://{tmp_path / 'by-id'}?addr=02")}  # fmt: skip
    assert keys == {f"serial {device}"}
    # a serial line behind a device server: its address and TCP port, whatever the scheme
    # or the unit, as Modbus TCP's host is
    server = {module_key("modbus-rtu://127.0.0.1:4001?unit=1"),
              module_key("ascii://localhost:4001?addr=02&baud=9600"),
              module_key("modbus-rtu://[::1]:4001?unit=7")}  # fmt: skip
    assert server == {"serial-tcp loopback:4001"}
    assert module_key("ascii://10.1.2.3:4001") == "serial-tcp 10.1.2.3:4001"
    apart = {module_key("ascii://10.1.2.3:4001"), module_key("ascii://10.1.2.3:4002"),
             module_key("modbus-tcp://10.1.2.3:4001"), *server}  # fmt: skip
    assert len(apart) == 4


def test_a_bad_url_is_a_value_error_naming_it():
    with pytest.raises(ValueError, match="unknown DAQ URL scheme"):
        module_key("can://vcan0")


@settings(max_examples=examples(100), deadline=None)
@given(st.text(max_size=120))
def test_any_key_gives_one_file_name_in_the_directory(tmp_path_factory, key):
    d = tmp_path_factory.getbasetemp()
    path = lock_path(key, d)
    assert path.parent == d and "/" not in path.name and len(path.name) < 100
    assert path == lock_path(key, d)


# ---------------------------------------------------------------------------- the lock


def test_a_second_lock_is_refused_naming_the_first(runtime_directory):
    url = "modbus-tcp://127.0.0.1:5020"
    with ModuleLock(url, command="loopcal record --daq ...") as first:
        with pytest.raises(ModuleHeld) as refused:
            ModuleLock("modbus-tcp://localhost:5020?unit=1", command="x")
        holder = refused.value.holder
        assert holder is not None and holder.pid == os.getpid() and not holder.service
        text = str(refused.value)
        assert f"another loopcal process (pid {os.getpid()}, `loopcal record --daq ...`" in text
        assert "loopcal session" in text and first.path.parent == runtime_directory
        # another module is free
        with ModuleLock("modbus-tcp://127.0.0.1:5021", command="y"):
            pass
    with ModuleLock(url, command="z") as again:  # released
        assert again.held


def test_the_service_is_named_and_a_session_offered(runtime_directory):
    with ModuleLock("modbus-tcp://127.0.0.1:5020", command="loopcal daemon --config /x/d.toml",
                    service=True):  # fmt: skip
        with pytest.raises(ModuleHeld, match=r"the loopcal service \(pid \d+.*"
                           r"loopcal session --config /x/d\.toml --until-enough"):  # fmt: skip
            ModuleLock("modbus-tcp://127.0.0.1:5020", command="x")


HOLD = """
import sys, time
from loopcal.daemon.recorder.ownership import ModuleLock
lock = ModuleLock(sys.argv[1], command="holder")
print("held", flush=True)
time.sleep(60)
"""


def test_a_holder_killed_leaves_the_module_free(runtime_directory):
    url = "modbus-tcp://127.0.0.1:5022"
    proc = subprocess.Popen([sys.executable, "-c", HOLD, url], stdout=subprocess.PIPE,
                            text=True)  # fmt: skip
    try:
        assert proc.stdout.readline().strip() == "held"
        with pytest.raises(ModuleHeld, match=rf"pid {proc.pid}"):
            ModuleLock(url, command="x")
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        proc.kill()
    with ModuleLock(url, command="x") as lock:  # the kernel released it
        # the dead holder's words were replaced by ours
        doc = json.loads(lock.path.read_text())
        assert doc["pid"] == os.getpid() and doc["command"] == "x"


def test_a_lock_file_naming_a_dead_process_names_nobody(runtime_directory):
    key = module_key("modbus-tcp://127.0.0.1:5023")
    path = lock_path(key)
    path.parent.mkdir(parents=True, exist_ok=True)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True).stdout.strip()  # fmt: skip
    path.write_text(json.dumps({"pid": int(dead), "command": "old", "service": True}))
    fd = os.open(path, os.O_RDONLY)
    try:
        assert Holder.read(fd) == Holder()
    finally:
        os.close(fd)
    for junk in (b"", b"{", b"[1]", b'{"pid": "x"}', b"\xff" * 10, b'{"pid": -1}'):
        path.write_bytes(junk)
        fd = os.open(path, os.O_RDONLY)
        try:
            assert Holder.read(fd) == Holder()
            assert "pid unknown" in Holder.read(fd).describe()
        finally:
            os.close(fd)


def test_a_runtime_directory_that_cannot_be_made_is_said(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("LOOPCAL_RUNTIME_DIR", str(tmp_path / "file" / "run"))
    with pytest.raises(ModuleHeld, match="cannot make the runtime directory .*LOOPCAL_RUNTIME_DIR"):
        ModuleLock("modbus-tcp://127.0.0.1:5024", command="x")


# ---------------------------------------------------------------------------- processes


@pytest.mark.slow
def test_a_second_recorder_of_the_daemons_module_is_refused_naming_it(tmp_path):
    sim = Proc(["simulate", "--speed", "4"])
    daemon = None
    try:
        url = listening_url(sim)
        cfg = write_config(tmp_path / "daemon.toml", url, tmp_path / "rec")
        daemon = Proc(["daemon", "--config", str(cfg)])
        daemon.wait_for("module_held: this process is the module's one owner")
        port = url.rsplit(":", 1)[1].split("?")[0]
        t0 = time.monotonic()
        second = loopcal("record", "--daq", f"modbus-tcp://localhost:{port}", "--out",
                         tmp_path / "mine", "--until-enough", timeout=60)  # fmt: skip
        took = time.monotonic() - t0
        assert second.returncode == 2, second.stderr
        err = second.stderr
        assert f"is already recorded by the loopcal service (pid {daemon.pid}" in err
        assert f"loopcal session --config {cfg}" in err
        assert not (tmp_path / "mine").exists()  # refused before anything was made
        assert took < 30  # at once: no connection tried (generous: a loaded machine)
        # another loopcal daemon of the same module: refused too, exit 2
        other = loopcal("daemon", "--config", write_config(tmp_path / "d2.toml", url,
                                                           tmp_path / "rec2"))  # fmt: skip
        assert other.returncode == 2 and f"(pid {daemon.pid}" in other.stderr
        rc, _ = daemon.stop()
        assert rc == 0
        daemon = None
        # the daemon gone, the module is free again
        mine = record(url, tmp_path / "mine", "--duration", "1")
        assert mine.wait(60) == 0, mine.text
    finally:
        if daemon is not None:
            daemon.kill()
        sim.kill()


def test_an_ascii_port_is_opened_exclusively(ldq412_factory):
    module = ldq412_factory(transport="ascii")
    with open_daq(module.url) as daq:
        daq.read_scans()
        # a program that is not loopcal, asking for the port exclusively as well behaved
        # serial programs do: refused while loopcal holds it
        with pytest.raises(serial.SerialException, match="exclusively"):
            serial.Serial(module.port, exclusive=True)
        # and loopcal's own driver, from a process whose lock directory differs, cannot
        # open it either
        with pytest.raises(DAQDisconnected, match="exclusively"):
            open_daq(module.url)
