"""``loopcal daemon`` and the recorder's resilience, as real subprocesses: its config file,
the systemd notify protocol on a real socket, SIGHUP, and disks that fail or stall."""

from __future__ import annotations

import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from loopcal.daemon.recorder.engine import Recorder
from loopcal.daemon.recorder.process import signal_handlers
from loopcal.daemon.recorder.settings import (
    RecorderSettings,
    SettingsError,
    load_daemon_config,
    parse_size,
)
from loopcal.daemon.recording import find_recordings, read_recordings
from tests.support.disk import can_mount, small_tmpfs
from tests.support.drivers import tcp_line
from tests.support.emulator import assert_matches_truth, hand_emulator
from tests.support.processes import (
    LOOPCAL,
    NotifySocket,
    Proc,
    cpu_seconds,
    free_port,
    record,
    scrape,
    value,
    write_config,
)

pytestmark = pytest.mark.timeout(120)


def consecutive(rows: np.ndarray) -> bool:
    return bool(np.all(np.diff(rows["counter64"].astype(np.int64)) == 1))


# ---------------------------------------------------------------------------- config


def test_a_full_config_loads(tmp_path):
    cfg = tmp_path / "daemon.toml"
    cfg.write_text(
        """
[daq]
url = "modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1"
timeout = 0.2
read_period = 0.5

[recording]
directory = "rec"
flush_period = 0.5
rotate_seconds = 600
rotate_size = "64 MiB"
disk_budget = "2 GiB"
max_backlog_scans = 100000

[controller]
config = "/etc/loopcal/controller/controller.toml"
""",
        encoding="utf-8",
    )
    s = load_daemon_config(cfg)
    assert s.directory == tmp_path / "rec"  # relative to the config file
    assert (s.timeout_s, s.read_period_s, s.flush_period_s) == (0.2, 0.5, 0.5)
    assert (s.rotate_seconds, s.rotate_bytes, s.disk_budget_bytes) == (600, 64 << 20, 2 << 30)
    assert s.max_backlog_scans == 100_000
    assert s.controller_config == Path("/etc/loopcal/controller/controller.toml")


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ("[recording.x]\n", r"\[recording\]\.x: unknown key"),
        ("rotate_secs = 5\n", r"\[recording\]\.rotate_secs: unknown key \(known: directory"),
        (
            "flush_period = 2.0\n",
            r"\[recording\]\.flush_period: must be >= 0.05 and <= 1 s, got 2.0",
        ),
        (
            "flush_period = 0.01\n",
            r"\[recording\]\.flush_period: must be >= 0.05 and <= 1 s, got 0.01",
        ),
        ('rotate_size = "lots"\n', r"\[recording\]\.rotate_size: 'lots' is not a size"),
        ("rotate_seconds = true\n", r"\[recording\]\.rotate_seconds: must be a number"),
        ('disk_budget = "1 MiB"\n', r"\[recording\]\.disk_budget: .* less than two files"),
        ("max_backlog_scans = 10\n", r"\[recording\]\.max_backlog_scans: must be an integer"),
        ("[watchdog]\nsec = 3\n", r"unknown table or key 'watchdog'"),
        ("keep_views_days = -1\n", r"\[recording\]\.keep_views_days: must be a number of days >="),
        ("keep_views_days = nan\n", r"\[recording\]\.keep_views_days: must be a number of days >="),
        ('keep_views_days = "7"\n', r"\[recording\]\.keep_views_days: must be a number of days"),
        ('[live]\nlisten = "8765"\n', r"\[live\]\.listen: .*HOST:PORT"),
    ],
)
def test_bad_configs_are_refused_naming_the_key(tmp_path, extra, message):
    cfg = write_config(tmp_path / "d.toml", "modbus-tcp://10.0.0.5", tmp_path, extra)
    with pytest.raises(SettingsError, match=message):
        load_daemon_config(cfg)


def test_views_are_kept_for_ever_or_a_week_by_default(tmp_path):
    cfg = write_config(tmp_path / "d.toml", "modbus-tcp://10.0.0.5", tmp_path)
    assert load_daemon_config(cfg).keep_views_days == 7.0
    cfg = write_config(tmp_path / "d.toml", "modbus-tcp://10.0.0.5", tmp_path,
                       "keep_views_days = inf\n")  # fmt: skip
    assert load_daemon_config(cfg).keep_views_days == float("inf")


def test_bad_daq_url_missing_keys_and_bad_toml(tmp_path):
    cfg = write_config(tmp_path / "d.toml", "modbus-tcp://h?baud=9600", tmp_path)
    with pytest.raises(SettingsError, match=r"\[daq\]\.url: .*unknown parameter.*baud"):
        load_daemon_config(cfg)
    cfg.write_text('[recording]\ndirectory = "/x"\n')
    with pytest.raises(SettingsError, match=r"\[daq\]\.url is required"):
        load_daemon_config(cfg)
    cfg.write_text("[daq\nurl=")
    with pytest.raises(SettingsError, match="not valid TOML"):
        load_daemon_config(cfg)
    with pytest.raises(SettingsError, match="cannot read"):
        load_daemon_config(tmp_path / "missing.toml")


def test_sizes():
    assert parse_size(4096) == 4096 and parse_size("256 MiB") == 256 << 20
    assert parse_size("1.5GiB") == 3 << 29 and parse_size("20 GB") == 20 * 10**9
    for bad in ("-1 MiB", "12 parsecs", True, 1.5):
        with pytest.raises(ValueError):
            parse_size(bad)
    with pytest.raises(SettingsError, match="--duration"):
        RecorderSettings("ascii:///dev/ttyS0", Path("/x"), duration_s=-1).checked()


@pytest.mark.slow
def test_daemon_exits_2_naming_the_problem(tmp_path):
    cfg = write_config(tmp_path / "d.toml", "modbus-tcp://10.0.0.5", tmp_path, "colour = 1\n")
    proc = subprocess.run([*LOOPCAL, "daemon", "--config", str(cfg)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2
    assert "[recording].colour: unknown key" in proc.stderr


# ---------------------------------------------------------------------------- systemd


@pytest.mark.slow
def test_daemon_speaks_the_notify_protocol_and_reloads_on_sighup(tmp_path):
    out = tmp_path / "rec"
    controller = tmp_path / "controller.toml"
    init = subprocess.run([*LOOPCAL, "init-config", str(controller)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert init.returncode == 0, init.stderr
    with hand_emulator() as emu:
        cfg = write_config(tmp_path / "daemon.toml", emu.url, out,
                           f'\n[controller]\nconfig = "{controller}"\n')  # fmt: skip
        notify = NotifySocket(tmp_path / "notify.sock")
        daemon = Proc(["daemon", "--config", str(cfg)],
                      env={"NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": "1000000",
                           "WATCHDOG_PID": ""})  # fmt: skip
        try:
            ready = notify.wait_for("READY", "1")
            assert "DAQ" in ready.get("STATUS", "") or "file" in ready.get("STATUS", "")
            t0 = time.monotonic()
            notify.wait_for("WATCHDOG", "1")
            notify.wait_for("WATCHDOG", "1")
            assert time.monotonic() - t0 < 2.5  # every half WATCHDOG_USEC
            status = notify.wait_for("STATUS", timeout=10)
            deadline = time.monotonic() + 10
            while (
                not (m := re.search(r"([\d,]+) scans written", status["STATUS"]))
                or int(m.group(1).replace(",", "")) == 0
            ):
                assert time.monotonic() < deadline, notify.messages
                status = notify.wait_for("STATUS")
            assert "DAQ connected" in status["STATUS"] and "recording loopcal-" in status["STATUS"]
            # reload with a changed controller config: a new file with the new parameters
            text = controller.read_text()
            controller.write_text(text.replace("d01 = 97.4", "d01 = 98.125"))
            daemon.signal(signal.SIGHUP)
            reloading = notify.wait_for("RELOADING", "1")
            assert abs(int(reloading["MONOTONIC_USEC"]) - time.monotonic_ns() // 1000) < 5e6
            notify.wait_for("READY", "1")
            daemon.wait_for("config_reload: configuration reloaded")
            daemon.wait_for(r"recording to .*", after=daemon.wait_for("config_reload"))
            time.sleep(1.5)
            # a broken config is refused: the daemon carries on as it was
            controller.write_text("[parameters]\nd01 = 'x'\n")
            daemon.signal(signal.SIGHUP)
            daemon.wait_for("config_reload: reload failed, keeping the running configuration")
            time.sleep(1.2)
            rc, took = daemon.stop()
            notify.wait_for("STOPPING", "1")
        finally:
            daemon.kill()
    assert rc == 0 and took < 2.0, daemon.text
    files = find_recordings(out)
    assert len(files) == 2, daemon.text
    first, second = (read_recordings([f]) for f in files)
    assert first.files[0].metadata["controller_config"]["d01"] == "97.4"
    assert second.files[0].metadata["controller_config"]["d01"] == "98.125"
    both = read_recordings(out)
    assert consecutive(both.scans) and both.scans["counter64"][0] == 0
    reloads = both.events_of("config_reload")
    assert [e.details["ok"] for e in reloads] == [True, False]


# ---------------------------------------------------------------------------- disks


@pytest.mark.slow
def test_a_file_size_limit_is_a_disk_error_and_nothing_is_lost(tmp_path):
    """RLIMIT_FSIZE makes writes fail with EFBIG, like a full disk; raising it again is
    like space coming back."""

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, resource.RLIM_INFINITY))

    with hand_emulator(rate=200) as emu:
        rec = record(emu.url, tmp_path, "--read-period", "0.1", preexec_fn=limit)
        rec.wait_for(r"disk_error: cannot write", timeout=30)
        cpu0, t0 = cpu_seconds(rec.pid), time.monotonic()
        time.sleep(3.0)
        cpu_share = (cpu_seconds(rec.pid) - cpu0) / (time.monotonic() - t0)
        assert rec.proc.poll() is None, rec.text
        resource.prlimit(rec.pid, resource.RLIMIT_FSIZE,
                         (resource.RLIM_INFINITY, resource.RLIM_INFINITY))  # fmt: skip
        rec.wait_for("disk_recovered: writing works again", timeout=15)
        time.sleep(1.0)
        rc, _ = rec.stop()
    assert rc == 0, rec.text
    assert cpu_share < 0.25, f"{cpu_share:.0%} of a core while the disk refused"
    out = read_recordings(tmp_path)
    rows = out.scans
    assert consecutive(rows) and rows["counter64"][0] == 0 and rows["missed"].sum() == 0
    assert_matches_truth(rows, emu)
    assert out.events_of("disk_error") and out.events_of("disk_recovered")
    assert all(f.scans for f in out.files)  # no empty husks left behind


@pytest.mark.slow
def test_a_directory_that_cannot_be_made_is_refused_at_start(tmp_path):
    blocker = tmp_path / "rec"
    blocker.write_text("a file where the directory should be")
    for out in (blocker, blocker / "sub"):
        rec = record("modbus-tcp://127.0.0.1:1", out, "--duration", "5")
        assert rec.wait(30) == 2, rec.text
        assert f"--out: {out}: " in rec.text and "Traceback" not in rec.text
    config = write_config(tmp_path / "daemon.toml", "modbus-tcp://127.0.0.1:1", blocker / "sub")
    proc = Proc(["daemon", "--config", str(config)])
    assert proc.wait(30) == 2, proc.text
    assert "[recording].directory" in proc.text and "Not a directory" in proc.text


@pytest.mark.slow
def test_a_directory_that_becomes_unwritable_recovers_when_fixed(tmp_path):
    top = tmp_path / "rec"
    port = free_port()
    with hand_emulator() as emu:
        rec = record(emu.url, top / "sub", "--metrics", f"127.0.0.1:{port}")
        rec.wait_for("recording to")
        time.sleep(1.0)
        top.rename(tmp_path / "moved")  # the open file goes on in moved/sub
        top.write_text("a file where the directory should be")
        rec.signal(signal.SIGHUP)  # a new file: it cannot be created
        rec.wait_for(r"disk_error: cannot write .*rec/sub", timeout=15)
        time.sleep(1.0)
        top.unlink()
        rec.wait_for("disk_recovered", timeout=15)
        m = scrape(port)
        time.sleep(1.0)
        rc, _ = rec.stop()
    assert rc == 0, rec.text
    out = read_recordings([tmp_path / "moved" / "sub", top / "sub"])
    assert consecutive(out.scans) and out.scans["counter64"][0] == 0
    assert out.events_of("disk_error")[0].details["errno"] in (20, 17, 2)  # ENOTDIR etc.
    # the writer's own events are counted in the metrics like every other
    assert value(m, "loopcal_events_total", kind="disk_error", level="error") == 1
    assert value(m, "loopcal_events_total", kind="disk_recovered", level="info") == 1
    assert value(m, "loopcal_disk_error") == 0


@pytest.mark.slow
@pytest.mark.skipif(not can_mount(), reason="mounting a small tmpfs needs root")
def test_a_full_filesystem_recovers_when_space_returns(tmp_path):
    with small_tmpfs(tmp_path / "small") as mnt:
        filler = mnt / "filler"
        filler.write_bytes(b"\0" * (960 << 10))
        with hand_emulator(rate=200) as emu:
            rec = record(emu.url, mnt / "rec", "--read-period", "0.1")
            rec.wait_for(r"disk_error: cannot write .*ENOSPC", timeout=30)
            time.sleep(6.0)  # at least one retry while still full
            assert rec.proc.poll() is None
            filler.unlink()
            rec.wait_for("disk_recovered", timeout=15)
            time.sleep(0.5)
            rc, _ = rec.stop()
        assert rc == 0, rec.text
        out = read_recordings(mnt / "rec")
        assert consecutive(out.scans) and out.scans["missed"].sum() == 0
        assert_matches_truth(out.scans, emu)


SLOW_FSYNC_C = r"""
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdlib.h>
#include <unistd.h>
int fsync(int fd) {
    static int (*real)(int);
    if (!real) real = (int (*)(int))dlsym(RTLD_NEXT, "fsync");
    const char *s = getenv("SLOW_FSYNC_S");
    if (s) usleep((useconds_t)(atof(s) * 1e6));
    return real(fd);
}
"""


FSYNC_S = 2.0  # the slow disk's fsync, s
RATE_HZ = 10  # the ASCII module's scan rate


@pytest.mark.slow
def test_a_stalling_disk_does_not_delay_reading(tmp_path):
    """fsync takes 2 s (a shim around the C library's fsync); the ASCII protocol has no
    FIFO, so a read held up by the disk would miss a whole fsync's worth of scans (20 at
    10 Hz), each time the writer flushes. Bounded by what a reader the disk blocked would
    show, not by how promptly a busy machine schedules it: no pause between two scans
    received as long as half an fsync, and fewer scans missed in all than a third of one
    fsync's worth; every scan missed is declared on the next."""
    src = tmp_path / "slow_fsync.c"
    src.write_text(SLOW_FSYNC_C)
    lib = tmp_path / "slow_fsync.so"
    gcc = shutil.which("gcc")
    assert gcc, "gcc builds the fsync shim (Debian's gcc is on every machine of this kind)"
    subprocess.run([gcc, "-shared", "-fPIC", "-o", str(lib), str(src), "-ldl"], check=True)
    env = {"LD_PRELOAD": str(lib), "SLOW_FSYNC_S": f"{FSYNC_S:g}"}
    probe = tmp_path / "probe"
    code = (f"import os,time; f=open({str(probe)!r},'wb'); t=time.monotonic(); "
            "os.fsync(f.fileno()); print(time.monotonic()-t)")  # fmt: skip
    check = subprocess.run([sys.executable, "-c", code], env={**os.environ, **env},
                           capture_output=True, text=True)  # fmt: skip
    assert float(check.stdout) >= FSYNC_S - 0.1, check  # the shim works
    with hand_emulator("ascii", rate=RATE_HZ, **tcp_line("ascii")) as emu:
        rec = record(emu.url, tmp_path / "rec", env=env)
        rec.wait_for("recording to", timeout=20)
        time.sleep(2 * FSYNC_S + 1)  # two fsyncs or more, back to back
        rc, _ = rec.stop(timeout=30)
    assert rc == 0, rec.text
    out = read_recordings(tmp_path / "rec")
    rows = out.scans
    c = rows["counter64"].astype(np.int64)
    assert np.array_equal(np.diff(c) - 1, rows["missed"][1:].astype(np.int64)), rec.text
    one_fsync = FSYNC_S * RATE_HZ
    assert len(rows) >= 2 * one_fsync and rows["missed"].sum() < one_fsync / 3, rec.text
    host_s = np.diff(rows["host_ns"]) / 1e9
    assert host_s.max() < FSYNC_S / 2, f"no scan received for {host_s.max():.2f} s"


def test_a_stop_or_reload_signal_takes_no_lock(tmp_path):
    """ci79: SIGTERM landed while the daemon's main thread, in the recorder's loop, held
    the stop event's own lock (inside Event.wait), and the handler's Event.set() waited for
    it forever: the daemon hung until it was killed. The handlers only note the signal,
    here called where it landed (a thread holding both events' locks stands for the main
    thread interrupted there: it must not wait for itself)."""
    settings = RecorderSettings(daq_url="modbus-tcp://127.0.0.1:1", directory=tmp_path / "rec")
    recorder = Recorder(settings.checked(), command="test")
    handlers = signal_handlers(recorder)
    landed = threading.Event()

    def interrupted_inside_wait() -> None:
        with recorder._stop._cond, recorder._reload._cond:
            handlers[signal.SIGHUP](signal.SIGHUP, None)
            handlers[signal.SIGTERM](signal.SIGTERM, None)
        landed.set()

    threading.Thread(target=interrupted_inside_wait, daemon=True).start()
    assert landed.wait(5), "a signal handler waited for a lock its own thread held"
    assert recorder._signalled_stop == "SIGTERM" and recorder._signalled_reload
