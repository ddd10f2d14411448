"""Writing the files people configure, so that nothing configured is ever lost or half
written: killed at any instant, a file is its old version or its new one; two writers are
serialised; a symlink stays a symlink.

- :func:`target_of`: the file a path names, through any symlinks. A controller that reads
  ``/opt/robot/config.toml`` through a link in ``/etc/loopcal`` must see the new values, so
  the link's target is what gets replaced, in its own directory, and the link is left alone.
- :func:`locked`: an advisory lock (``flock``) on the target's directory, held by a writer
  from the moment it reads the file to the moment the new version is in place, so that a
  second writer waits and then sees what the first one wrote (no lock file is left behind).
- :func:`create_new`: a new file, durably, never over an existing one; :func:`make_dirs`,
  new directories, durably.
- :func:`replace`: a new version of a file (temporary file in the same directory, fsync,
  rename over it, fsync of the directory), with the old file's mode and, where allowed, its
  owner.

Fault injection for tests: ``step(name)`` calls let a test SIGKILL the process right after
a named step (``LOOPCAL_KILL_AT=name``) or hold it there for a while
(``LOOPCAL_PAUSE_AT=name:seconds``), as the emulator's faults do for the wire.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import re
import secrets
import signal
import time
from collections.abc import Callable, Iterator
from glob import escape as glob_escape
from pathlib import Path

#: how long a writer waits for another to finish before giving up, s
LOCK_TIMEOUT_S = 30.0


class Busy(OSError):
    """Another writer held the lock for longer than the timeout."""


def step(name: str) -> None:
    """A named point in a write sequence, where tests inject a kill or a pause."""
    if os.environ.get("LOOPCAL_KILL_AT") == name:
        os.kill(os.getpid(), signal.SIGKILL)
    pause = os.environ.get("LOOPCAL_PAUSE_AT", "")
    if pause.partition(":")[0] == name:
        time.sleep(float(pause.partition(":")[2] or 1.0))


def fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def make_dirs(directory: Path) -> None:
    """``mkdir -p`` that a power cut does not undo: each directory created, its parent
    synced. Nothing done when ``directory`` is one. FileExistsError when it is something
    else, NotADirectoryError (naming it) when a parent is."""
    missing = []
    p = Path(directory)
    while not p.exists() and p.parent != p:
        missing.append(p)
        p = p.parent
    if not p.is_dir():
        if not missing:
            raise FileExistsError(errno.EEXIST, "exists and is not a directory", str(p))
        raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(p))
    for d in reversed(missing):
        d.mkdir(exist_ok=True)
        with contextlib.suppress(PermissionError):  # a parent we may write but not read
            fsync_dir(d.parent)


def target_of(path: Path) -> Path:
    """The file ``path`` names: itself, or where its chain of symlinks ends (which need not
    exist yet). Raises OSError for a symlink loop."""
    if not path.is_symlink():
        return path
    return Path(os.path.realpath(path, strict=False))


@contextlib.contextmanager
def locked(target: Path, timeout: float = LOCK_TIMEOUT_S) -> Iterator[None]:
    """Hold the advisory write lock of ``target``: ``flock`` on its directory (the
    directory, not the file, because the file is replaced by another inode on every
    write).

    Raises :class:`Busy` after ``timeout`` s, and OSError if the directory cannot be opened.
    """
    fd = os.open(target.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise Busy(errno.EWOULDBLOCK, f"another writer has held the lock on "
                               f"{target.parent} for {timeout:g} s") from None  # fmt: skip
                time.sleep(0.05)
        yield
    finally:
        os.close(fd)  # releases the lock


def check_can_replace(target: Path) -> None:
    """Raise OSError unless ``target`` is a regular file whose directory takes new files
    (what :func:`replace` needs), by creating and removing a temporary file there."""
    if not target.is_file():
        raise FileNotFoundError(errno.ENOENT, "no such file", str(target))
    _write_tmp(target.parent, target.name, b"", 0o600, None).unlink()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def sweep_temporaries(directory: Path, name: str) -> list[Path]:
    """Remove the temporary files of ``name`` in ``directory`` that a writer killed before
    its rename left (``.{name}.{pid}.{token}.tmp`` whose process is gone); those of a
    writer still running are left to it. Returns those removed."""
    gone = []
    for tmp in directory.glob(f".{glob_escape(name)}.*.*.tmp"):
        m = re.fullmatch(r"(\d+)\.[0-9a-f]{8}\.tmp", tmp.name[len(name) + 2 :])
        if m is not None and not _alive(int(m.group(1))):
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
                gone.append(tmp)
    return gone


def _write_tmp(directory: Path, name: str, data: bytes, mode: int,
               owner: tuple[int, int] | None) -> Path:  # fmt: skip
    """Write ``data`` to a new temporary file in ``directory`` and fsync it (what a killed
    writer of the same file left there removed first: :func:`sweep_temporaries`)."""
    sweep_temporaries(directory, name)
    tmp = directory / f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o600)
    try:
        if owner is not None:
            with contextlib.suppress(PermissionError):  # only root may give files away
                os.fchown(fd, *owner)
        os.fchmod(fd, mode)  # the old file's mode, whatever the umask
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    os.close(fd)
    return tmp


def create_new(path: Path, data: bytes, mode: int, *,
               on_step: Callable[[str], None] = step, prefix: str = "") -> None:  # fmt: skip
    """Create ``path`` holding ``data``, durably, never replacing an existing file
    (FileExistsError). Steps: ``{prefix}written`` (data synced in a temporary file),
    ``{prefix}renamed`` (in place), then the directory is synced."""
    tmp = _write_tmp(path.parent, path.name, data, mode, None)
    try:
        on_step(f"{prefix}written")
        os.link(tmp, path)  # unlike rename, never over an existing file
    finally:
        tmp.unlink(missing_ok=True)
    on_step(f"{prefix}renamed")
    fsync_dir(path.parent)


def replace(target: Path, data: bytes, *, mode: int | None = None,
            on_step: Callable[[str], None] = step, prefix: str = "") -> None:  # fmt: skip
    """Atomically make ``target`` hold ``data``: a temporary file in its directory, synced,
    renamed over it, and the directory synced. ``mode`` default: the old file's (else
    0o644 less the umask); the old file's owner and group are kept where allowed. Steps:
    ``{prefix}written`` (synced, not yet in place), ``{prefix}renamed``, ``{prefix}synced``
    (directory synced)."""
    owner = None
    try:
        st = os.stat(target)
        owner = (st.st_uid, st.st_gid)
        if mode is None:
            mode = st.st_mode & 0o7777
    except FileNotFoundError:
        pass
    if mode is None:
        umask = os.umask(0)
        os.umask(umask)
        mode = 0o666 & ~umask
    tmp = _write_tmp(target.parent, target.name, data, mode, owner)
    try:
        on_step(f"{prefix}written")
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    on_step(f"{prefix}renamed")
    fsync_dir(target.parent)
    on_step(f"{prefix}synced")
