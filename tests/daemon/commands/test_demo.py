"""The README's main command, `loopcal demo`, as a real subprocess: record a technician's
session through the emulated DAQ, calibrate it, write the config, compare with the truth,
end with a verdict. The commands it shows are checked against the processes it really ran
(their command lines in /proc while they run)."""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from loopcal.calibration.parameters import INDEX
from loopcal.daemon.config.controller import load_controller_config, nominal_config
from tests.support.processes import loopcal_main

ENTRY = [sys.executable, "-m", "loopcal.daemon.cli"]


@dataclass
class Demo:
    returncode: int
    lines: list[tuple[float, str]]  # (seconds since start, line) as they came on stdout
    stderr: str
    children: list[list[str]] = field(default_factory=list)  # argv of each child seen

    @property
    def stdout(self) -> str:
        return "".join(line for _, line in self.lines)

    def shown(self, command: str) -> list[str]:
        """The `$ loopcal COMMAND ...` line it printed, split as a shell splits it."""
        (line,) = [ln for _, ln in self.lines if ln.startswith(f"$ loopcal {command} ")]
        return shlex.split(line[2:])

    def shown_through_bash(self, command: str) -> list[str]:
        """The same line pasted into bash (failglob: an unquoted `?` would be a glob)."""
        (line,) = [ln for _, ln in self.lines if ln.startswith(f"$ loopcal {command} ")]
        words = subprocess.run(
            ["bash", "-O", "failglob", "-c", "printf '%s\\0' " + line[2:]],
            capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
        return words.split("\0")[:-1]

    def ran(self, command: str) -> list[list[str]]:
        """Every `loopcal COMMAND` process it started, as its argv (entry point dropped)."""
        return [c[len(ENTRY) :] for c in self.children if c[: len(ENTRY) + 1] == [*ENTRY, command]]


def _children(pid: int) -> list[list[str]]:
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) != pid:
                continue
            argv = (d / "cmdline").read_bytes().split(b"\0")[:-1]
        except (OSError, IndexError, ValueError):
            continue  # gone meanwhile
        out.append([a.decode() for a in argv])
    return out


def run_demo(*args: str, timeout: float = 150) -> Demo:
    proc = subprocess.Popen(
        [*ENTRY, "demo", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    t0 = time.monotonic()
    seen: list[list[str]] = []
    err: list[str] = []

    def watch() -> None:
        while proc.poll() is None:
            seen.extend(c for c in _children(proc.pid) if c not in seen)
            time.sleep(0.05)

    threads = [
        threading.Thread(target=watch, daemon=True),
        threading.Thread(target=lambda: err.append(proc.stderr.read()), daemon=True),
    ]
    for t in threads:
        t.start()
    timer = threading.Timer(timeout, proc.kill)
    timer.start()
    lines = [(time.monotonic() - t0, line) for line in proc.stdout]
    proc.wait()
    timer.cancel()
    for t in threads:
        t.join()
    return Demo(proc.returncode, lines, "".join(err), seen)


def table(out: str) -> dict[str, tuple[float, ...]]:
    rows = re.findall(r"^\s+(d0\d|A1x|A2x|A2y)\s+mm\s+(\S+\s+\S+\s+\S+\s+\S+\s+\S+)$", out, re.M)
    return {name: tuple(float(v) for v in cols.split()) for name, cols in rows}


@pytest.mark.slow
def test_demo_writes_offsets_close_to_the_truth(tmp_path):
    demo = run_demo("--out", str(tmp_path / "a dir"), "--seed", "2", "--speed", "20")
    out = demo.stdout
    assert demo.returncode == 0, out + demo.stderr
    assert "Wrote 10 value(s)" in out
    rows = table(out)
    assert set(rows) == {"d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"}
    written = load_controller_config(tmp_path / "a dir" / "controller.toml")
    for name, (value, _truth, error, std, z) in rows.items():
        assert abs(z) < 3.5 and std < 0.25 and abs(error) < 0.5, name
        assert abs(written.params[INDEX[name]] - value) < 1e-3
    assert (tmp_path / "a dir" / "report" / "index.html").exists()
    assert float(re.search(r"Done in ([\d.]+) s", out).group(1)) < 60
    # the verdict is the last line, and its bound is the table's worst |err/std| rounded up
    verdict = demo.lines[-1][1].rstrip("\n")
    m = re.fullmatch(r"verdict: written, every parameter within ([\d.]+) std of the truth", verdict)
    assert m, verdict
    worst = max(abs(error / std) for _, _, error, std, _ in rows.values())
    assert worst <= float(m.group(1)) < worst + 0.1 + 1e-9
    # nothing from the emulated module's pymodbus server on the demo's stderr
    assert "pymodbus" not in demo.stderr and "Cancel send" not in demo.stderr, demo.stderr


@pytest.mark.slow
def test_demo_shows_the_commands_it_really_runs(tmp_path):
    """The printed command lines paste into a shell as they are: split by shlex or by bash
    (the URL's `?`, a path with a space), they are the argv of the processes the demo ran."""
    demo = run_demo("--out", str(tmp_path / "with space"), "--duration", "12")
    assert demo.returncode == 1, demo.stdout + demo.stderr  # too short: refused
    assert demo.stderr == ""  # the commands' output is all on stdout, in order
    for command in ("record", "calibrate"):
        shown = demo.shown(command)
        assert shown[0] == "loopcal"
        assert demo.ran(command) == [shown[1:]], (shown, demo.children)
        assert demo.shown_through_bash(command) == shown
    record = demo.shown("record")
    assert record[record.index("--daq") + 1].startswith("modbus-tcp://127.0.0.1:")
    assert "?unit=1" in record[record.index("--daq") + 1]
    assert record[record.index("--duration") + 1] == "1.2"  # 12 s at x10
    assert record[record.index("--out") + 1] == str(tmp_path / "with space" / "recordings")


@pytest.mark.slow
def test_demo_too_short_says_nothing_was_written_and_where_its_files_are():
    """Refused, in a temporary directory kept by --keep: the end lists the files in it,
    just before the verdict, and the config there is as init-config wrote it."""
    demo = run_demo("--duration", "6s", "--keep")
    out = demo.stdout
    assert demo.returncode == 1, out + demo.stderr
    start = next(i for i, (_, ln) in enumerate(demo.lines) if ln.startswith("Its files, in "))
    work = Path(demo.lines[start][1].removeprefix("Its files, in ").removesuffix(":\n"))
    try:
        listed = [ln.split(": ")[0].strip() for _, ln in demo.lines[start + 1 : -1]]
        assert listed == [str(work / "recordings"), str(work / "controller.toml"),
                          str(work / "report" / "index.html")], demo.lines[start:]  # fmt: skip
        assert all(Path(f).exists() for f in listed)
        assert "against the truth" not in out and not re.search(r"\bnan\b", out)
        assert not table(out)
        # six seconds of motion: refused, and the verdict quotes the first gate that failed
        failed = re.findall(r"^  \[FAIL\] (\S+): .*\n\s+why: (.*)$", out, re.M)
        assert failed, out
        name, why = failed[0]
        assert re.search(
            rf"^Nothing was written: loopcal calibrate refused the session \({name}: ", out, re.M
        )
        assert demo.lines[-1][1].startswith(f"verdict: refused ({name}: {why}")
        assert demo.lines[-1][1].endswith("), nothing written\n")
        # and indeed nothing was: the config is what init-config wrote, no previous version
        config = load_controller_config(work / "controller.toml")
        assert config.provenance is None
        assert list(config.params) == list(nominal_config().params)
        assert [p.name for p in work.iterdir() if p.name.startswith("controller.toml")] == [
            "controller.toml"
        ]
    finally:
        shutil.rmtree(work, ignore_errors=True)


@pytest.mark.slow
def test_ascii_demo_shows_progress_while_it_records(tmp_path):
    """Over ASCII the module runs in real time: the demo says how far it has come at least
    every few seconds, in the session's own time: never more than has passed, nor beyond
    the session's end."""
    demo = run_demo("--transport", "ascii", "--duration", "0.2m", "--out", str(tmp_path))
    # 12 s of motion: written or refused (every scan counts: the precision gate may pass)
    assert demo.returncode in (0, 1), demo.stdout + demo.stderr
    assert demo.shown("record")[:3] == ["loopcal", "record", "--daq"]
    start = next(i for i, (_, ln) in enumerate(demo.lines) if ln.startswith("$ loopcal record"))
    stop = next(i for i, (_, ln) in enumerate(demo.lines) if "stopped (--duration" in ln)
    during = demo.lines[start : stop + 1]
    t_start = during[0][0]
    assert during[-1][0] - t_start >= 12
    assert max(b[0] - a[0] for a, b in zip(during, during[1:], strict=False)) < 8, during
    waiting = "  recording: waiting for loopcal record to talk to the module\n"
    seconds = []
    for t, line in during[1:-1]:
        m = re.fullmatch(r"  recording: (\d+):(\d\d) of 0:12\n", line)
        assert m or line == waiting, line
        if m:
            seconds.append(60 * int(m.group(1)) + int(m.group(2)))
            assert seconds[-1] <= min(12, t - t_start + 1), (t - t_start, line)
    assert len(seconds) >= 2 and seconds == sorted(seconds) and seconds[-1] >= 5, during
    assert re.match(r"verdict: (written|refused)\b", demo.lines[-1][1]), demo.lines[-1]
    # what it wrote over ASCII is within its bounds
    assert all(abs(z) < 3.5 for *_, z in table(demo.stdout).values())


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--duration", "0"], "--duration: '0': a duration must be more than 0"),
     (["--free", "Q7"], "unknown parameter"),
     (["--twist-every", "-1"], "--twist-every must be 0 or more moves, got -1")],
)  # fmt: skip
def test_demo_bad_options(args, message):
    refused = loopcal_main("demo", *args)  # in this process: refused before anything starts
    assert refused.returncode == 2
    assert message in refused.stderr


@pytest.mark.slow
def test_demo_json_is_one_object_that_matches_the_config_written(tmp_path):
    import json

    demo = run_demo("--out", str(tmp_path), "--seed", "3", "--json", "--speed", "20")
    assert demo.returncode == 0, demo.stdout + demo.stderr
    doc = json.loads(demo.stdout)  # stdout holds the object alone; the session went to stderr
    assert "$ loopcal record " in demo.stderr and "verdict: " in demo.stderr
    assert doc["exit_status"] == 0 and doc["written"] is True and doc["work"] == str(tmp_path)
    assert doc["verdict"] == demo.stderr.rstrip("\n").splitlines()[-1].removeprefix("verdict: ")
    written = load_controller_config(tmp_path / "controller.toml")
    assert set(doc["parameters"]) == {"d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"}
    for name, p in doc["parameters"].items():
        assert p["written"] == written.params[INDEX[name]], name
        assert p["error"] == pytest.approx(p["written"] - p["truth"], abs=1e-12)
        assert p["std"] == written.provenance["std"][name] and abs(p["error"]) < 3.5 * p["std"]


@pytest.mark.slow
def test_demo_removes_its_temporary_directory_and_says_how_to_keep_it():
    """Without --out or --keep the end says where the files were, that they are removed,
    and how to keep them; and they are gone."""
    gone = run_demo("--duration", "3")
    assert gone.returncode == 1, gone.stdout + gone.stderr  # too short: refused
    m = re.fullmatch(r"Its files were in (\S+), removed as the demo ends: --keep keeps them, "
                     r"--out DIR puts them where you choose\.\n", gone.lines[-2][1])  # fmt: skip
    assert m, gone.lines[-3:]
    assert not Path(m.group(1)).exists()
