"""``loopcal probe URL``: exit 0 and what the module is, 1 and the cause (a device the user
may not open, asked of a process that is not root; a module a recorder holds, named), 2
for a bad URL or option; a help that imports no numpy."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from loopcal.daemon.recorder.ownership import ModuleLock
from loopcal.drivers.probe import PROBE_BUDGET_S
from loopcal.simulator.clock import ManualClock
from loopcal.simulator.emulator import Emulator
from tests.support.processes import LOOPCAL, free_port, loopcal_main

OK_TIMEOUT = "1"  # the emulator in this process must answer (tests/support/drivers.py)


def _json(*args: str) -> tuple[int, dict]:
    proc = loopcal_main("probe", *args, "--json")
    return proc.returncode, json.loads(proc.stdout)


def test_help_imports_no_numpy() -> None:
    """What ``python -X importtime`` says ``loopcal probe --help`` imported: none of the
    heavy parts, which the command imports in ``run``."""
    proc = subprocess.run([sys.executable, "-X", "importtime", *LOOPCAL[1:], "probe", "--help"],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0 and "usage: loopcal probe" in proc.stdout, proc.stderr
    rows = [line for line in proc.stderr.splitlines() if line.startswith("import time:")]
    imported = {row.rsplit("|", 1)[1].strip().split(".")[0] for row in rows}
    assert "loopcal" in imported and "argparse" in imported  # the table is there
    assert not imported & {"numpy", "scipy", "pymodbus", "serial", "mcap"}, sorted(imported)


def test_the_module_found_is_exit_0_and_said_in_words_and_json() -> None:
    with Emulator("modbus-tcp", clock=ManualClock()) as emu:
        emu.clock.advance(1.0)
        status, doc = _json(emu.url, "--timeout", OK_TIMEOUT)
        text = loopcal_main("probe", emu.url, "--timeout", OK_TIMEOUT)
    assert status == 0 and doc["found"] is True and doc["cause"] is None
    assert doc["elapsed_s"] <= PROBE_BUDGET_S and doc["budget_s"] == PROBE_BUDGET_S
    assert doc["identity"] == {"model": "LDQ412", "firmware": "2.01", "serial": 0x00C0FFEE,
                               "model_code": 0x0412}  # fmt: skip
    assert set(doc) == {"url", "found", "cause", "message", "hint", "identity", "module",
                        "rtt_ms", "tried", "answered_url", "notes", "details", "elapsed_s",
                        "budget_s", "timeout_s"}  # fmt: skip
    assert text.returncode == 0, text.stderr
    out = text.stdout
    assert out.startswith(f"found: LDQ412 firmware 2.01, serial 12648430 answers at {emu.url}")
    assert "serial 12648430 (0x00c0ffee)" in out and "scan rate     20 Hz" in out
    assert re.search(r"FIFO +\d+ scans waiting; overflow flag clear", out)
    assert "restart flag  set: powered on since a recorder last cleared it" in out
    assert re.search(r"round trip +median [\d.]+ ms", out)


def test_a_cause_is_exit_1_with_the_hint_and_what_was_tried() -> None:
    port = free_port()
    proc = loopcal_main("probe", f"modbus-tcp://127.0.0.1:{port}")
    assert proc.returncode == 1 and proc.stderr == ""
    lines = proc.stdout.splitlines()
    assert lines[0] == f"not found [refused]: nothing listens at 127.0.0.1:{port} (connection " \
        "refused)"  # fmt: skip
    assert lines[1].startswith("hint: is the module powered")
    assert lines[2] == "tried (1):"
    assert re.fullmatch(rf"  modbus-tcp://127\.0\.0\.1:{port}: cannot connect \(\d+\.\d\d s\)",
                        lines[3])  # fmt: skip
    assert re.fullmatch(r"probed in \d+\.\d\d s \(budget 5 s, 0\.1 s for each answer\)", lines[4])


@pytest.mark.parametrize(("argv", "words"), [
    (["nope://x"], "unknown DAQ URL scheme 'nope'"),
    (["modbus-tcp://127.0.0.1:502?unit=300"], "unit=300 is outside 1..247"),
    (["modbus-tcp://127.0.0.1:502", "--timeout", "2"], "--timeout 2 s: at most 1 s"),
    (["modbus-tcp://127.0.0.1:502", "--timeout", "soon"], "is not a duration"),
    ([], "the following arguments are required: URL"),
])  # fmt: skip
def test_a_bad_url_or_option_is_exit_2(argv: list[str], words: str) -> None:
    proc = loopcal_main("probe", *argv)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    errors = [line for line in proc.stderr.splitlines() if "error" in line]
    assert errors == [line for line in errors if line.startswith("loopcal probe: error: ")]
    assert len(errors) == 1 and words in errors[0], proc.stderr


def test_a_module_a_recorder_holds_is_not_probed_and_its_pid_named() -> None:
    with Emulator("modbus-tcp", clock=ManualClock()) as emu:
        with ModuleLock(emu.url, command="loopcal record --daq URL --out DIR"):
            status, doc = _json(emu.url)
        requests = emu.first_request.is_set()
    assert status == 1 and doc["cause"] == "busy" and doc["tried"] == []
    assert f"is recorded by another loopcal process (pid {os.getpid()}, `loopcal record" \
        in doc["message"]  # fmt: skip
    assert doc["details"]["holder"]["pid"] == os.getpid() and "stop it first" in doc["hint"]
    assert not requests  # not a byte sent to the module


_SETPRIV = shutil.which("setpriv")


@pytest.mark.skipif(_SETPRIV is None or os.geteuid() != 0,
                    reason="needs setpriv (util-linux), and root to run a probe as nobody")
def test_a_device_the_user_may_not_open_names_its_group(tmp_path: Path) -> None:
    """A serial device as udev makes a USB adapter (root:dialout 0660), probed by a user
    outside dialout, then by one in it."""
    runtime = tmp_path / "run"
    runtime.mkdir(mode=0o777)
    runtime.chmod(0o777)
    env = {**os.environ, "LOOPCAL_RUNTIME_DIR": str(runtime)}
    with Emulator("modbus-rtu", clock=ManualClock()) as emu:
        device = emu.url.split("://", 1)[1].split("?", 1)[0]
        shutil.chown(device, group="dialout")
        os.chmod(device, 0o660)

        def probe_as(*groups: str) -> dict:
            who = ["--groups", ",".join(groups)] if groups else ["--clear-groups"]
            proc = subprocess.run(
                [_SETPRIV, "--reuid=nobody", "--regid=nogroup", *who, *LOOPCAL, "probe",
                 emu.url, "--json", "--timeout", OK_TIMEOUT],
                capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path,
            )  # fmt: skip
            assert proc.returncode in (0, 1), proc.stderr
            return json.loads(proc.stdout)

        refused = probe_as()
        allowed = probe_as("dialout")
    assert refused["cause"] == "permission" and refused["tried"] == []
    assert refused["message"] == f"permission denied on {device} (crw-rw----, group dialout)"
    assert refused["hint"].startswith("user nobody is not in group dialout: `sudo usermod -aG "
                                      "dialout nobody`")  # fmt: skip
    assert refused["details"]["in_group"] is False
    assert refused["elapsed_s"] <= PROBE_BUDGET_S
    assert allowed["found"] is True, allowed
