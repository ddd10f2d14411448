"""What a writer killed mid-write leaves, and new directories that a power cut keeps."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from loopcal.daemon.config import durable


def dead_pid() -> int:
    """The pid of a process that has exited."""
    proc = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        capture_output=True,
        text=True,
        check=True,
    )
    return int(proc.stdout)


def temporaries(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


def test_the_temporaries_a_killed_writer_left_go_with_the_next_write(tmp_path):
    target = tmp_path / "controller.toml"
    target.write_text("old\n")
    env = {**os.environ, "LOOPCAL_KILL_AT": "written"}
    code = (
        f"from pathlib import Path; from loopcal.daemon.config import durable; "
        f"durable.replace(Path({str(target)!r}), b'new\\n')"
    )
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    left = temporaries(tmp_path)
    assert (
        len(left) == 1 and left[0].startswith(".controller.toml.") and target.read_text() == "old\n"
    )
    durable.replace(target, b"newer\n")
    assert temporaries(tmp_path) == [] and target.read_text() == "newer\n"


def test_a_running_writers_temporary_and_other_files_are_left_alone(tmp_path):
    target = tmp_path / "controller.toml"
    target.write_text("old\n")
    dead, alive = dead_pid(), os.getpid()
    names = [
        f".controller.toml.{dead}.0123abcd.tmp",  # killed: removed
        f".controller.toml.{alive}.89abcdef.tmp",  # its writer runs
        f".controller.toml.proposed.{dead}.0123abcd.tmp",  # another file's
        f".controller.toml.{dead}.notatoken.tmp",  # not one of ours
        f".controller.toml.{dead}.0123abcd.tmp.bak",
    ]
    for n in names:
        (tmp_path / n).write_text("x")
    durable.replace(target, b"new\n")
    assert not (tmp_path / names[0]).exists()
    assert all((tmp_path / n).exists() for n in names[1:])
    gone = durable.sweep_temporaries(tmp_path, "controller.toml.proposed")
    assert gone == [tmp_path / names[2]]


def test_new_directories_are_synced_into_their_parents(tmp_path, monkeypatch):
    synced = []
    real = durable.fsync_dir
    monkeypatch.setattr(durable, "fsync_dir", lambda d: (synced.append(Path(d)), real(d)))
    deep = tmp_path / "a" / "b" / "recordings"
    durable.make_dirs(deep)
    assert deep.is_dir() and synced == [tmp_path, tmp_path / "a", tmp_path / "a" / "b"]
    synced.clear()
    durable.make_dirs(deep)  # there already: nothing to do
    assert synced == []
    (tmp_path / "file").write_text("")
    with pytest.raises(FileExistsError):
        durable.make_dirs(tmp_path / "file")
    with pytest.raises(NotADirectoryError, match="file"):
        durable.make_dirs(tmp_path / "file" / "below")
