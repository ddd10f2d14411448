"""``loopcal compact`` on what is not a recording (issue 20): bad input exits 2 with one
``loopcal compact: error: ...`` line naming the problem, before any file is touched; a
recording that is damaged, and so left alone, exits 1; nothing hangs, nothing raises."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from mcap.writer import Writer

from loopcal.daemon import recording as rec
from tests.support.mutations import tear_chunk
from tests.support.recordings import not_recordings, write_recording
from tests.support.rows import T0, make_rows

pytestmark = pytest.mark.timeout(180)


def _compact(*argv: str | Path) -> subprocess.CompletedProcess:
    """``loopcal compact ARGV`` in a process of its own; a hang fails the test (timeout)."""
    return subprocess.run([sys.executable, "-m", "loopcal.daemon.cli", "compact", *map(str, argv)],
                          capture_output=True, text=True, timeout=60)  # fmt: skip


def _bad_input(proc: subprocess.CompletedProcess, words: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    lines = proc.stderr.splitlines()
    errors = [line for line in lines if line.startswith("loopcal compact: error: ")]
    assert errors and words in errors[0], proc.stderr
    assert "Traceback" not in proc.stderr


def _recording(directory: Path, k: int = 0) -> Path:
    path = directory / rec.recording_name(T0 + k * 10**12)
    write_recording(path, make_rows(600))
    return path


def _foreign_mcap(path: Path) -> Path:
    """An MCAP file of something else: one channel, /camera/info, of JSON."""
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="someone else")
        sid = w.register_schema("Info", "jsonschema", b"{}")
        cid = w.register_channel("/camera/info", "json", sid)
        for k in range(10):
            w.add_message(cid, T0 + k, b"{}", T0 + k)
        w.finish()
    return path


@pytest.mark.slow
def test_what_is_not_a_recording_is_bad_input(tmp_path):
    strangers = not_recordings(tmp_path)
    text = tmp_path / "x.mcap"
    foreign = _foreign_mcap(tmp_path / "camera.mcap")
    before = {p: p.read_bytes() for p in (text, foreign)}
    for argv, words in (
        *strangers,
        ([foreign], f"{foreign}: an MCAP file but not a loopcal recording"),
        (["--json", text], f"{text}: not an MCAP file"),
    ):
        _bad_input(_compact(*argv), words)
    assert {p: p.read_bytes() for p in before} == before  # each left exactly as it was
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.slow
def test_bad_input_is_refused_before_any_file_is_touched(tmp_path):
    good = _recording(tmp_path)
    data = good.read_bytes()
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    _bad_input(_compact(good, text), f"{text}: not an MCAP file")
    assert good.read_bytes() == data  # not compacted: nothing was done
    _bad_input(_compact(good, "/etc/passwd"), "/etc/passwd: not an MCAP file")
    assert good.read_bytes() == data


@pytest.mark.slow
def test_a_stranger_found_in_a_directory_is_named_and_exits_2(tmp_path):
    """A file named like a recording that is an MCAP file of something else: the
    recordings beside it are compacted, the stranger is left as it is and named."""
    good = _recording(tmp_path)
    stranger = _foreign_mcap(tmp_path / rec.recording_name(T0 + 10**12))
    data = stranger.read_bytes()
    proc = _compact(tmp_path)
    _bad_input(proc, f"{stranger}: an MCAP file but not a loopcal recording")
    assert f"{good}: " in proc.stdout and "chunks ->" in proc.stdout, proc.stdout
    assert stranger.read_bytes() == data
    assert "compacted_utc" in rec.read_recordings(good).files[0].metadata["loopcal"]


@pytest.mark.slow
def test_a_fifo_in_a_directory_is_not_waited_on(tmp_path):
    """A FIFO named like a recording in the directory is not a recording file: skipped,
    never opened (a reader would block on it)."""
    good = _recording(tmp_path)
    os.mkfifo(tmp_path / rec.recording_name(T0 + 10**12))
    proc = _compact(tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert f"{good}: " in proc.stdout and "chunks ->" in proc.stdout, proc.stdout


@pytest.mark.slow
def test_a_damaged_recording_is_left_alone_and_exits_1(tmp_path):
    damaged = _recording(tmp_path)
    data = tear_chunk(damaged, 4)
    junk = tmp_path / rec.recording_name(T0 + 10**12)  # named like one: a recording whose
    junk.write_bytes(os.urandom(5000))  # every byte was lost, not a stranger
    for argv in ([damaged], [tmp_path]):
        proc = _compact(*argv)
        assert proc.returncode == 1, (argv, proc.stdout, proc.stderr)
        assert "damaged" in proc.stdout and "error:" not in proc.stderr, proc.stdout + proc.stderr
        assert "Traceback" not in proc.stderr
    assert damaged.read_bytes() == data
    (tmp_path / "good").mkdir()
    proc = _compact(_recording(tmp_path / "good"))
    assert proc.returncode == 0 and "chunks ->" in proc.stdout, proc.stdout + proc.stderr
