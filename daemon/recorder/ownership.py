"""One owner of a module on this host: an advisory lock per module.

The LDQ-412's FIFO gives each scan to whoever reads it first, so two processes recording
one module split its scans between them, silently. A recorder (``loopcal record``,
``loopcal daemon``) therefore takes an exclusive ``flock`` on a lock file named after the
module before it opens it, and keeps it as long as it runs; a second one is refused at
once, with the holder named. The kernel releases the lock when the holder's process ends,
however it ends, so a crash never leaves a module locked. The lock file itself stays (it
is how the next holder finds the lock) and says who holds it: pid, command, since when,
and whether it is the service.

Two URLs name the same module when they reach the same endpoint from this host:

- Modbus TCP: the host's address (a name is resolved; every loopback address is one),
  the port (502 by default) and the unit (1 by default);
- a serial line (Modbus RTU, ASCII): the device, its symlinks resolved
  (``/dev/serial/by-id/...`` is the ``/dev/ttyUSB0`` it points to), or, for a line behind
  a serial device server (``ascii://HOST:PORT``), the device server's address and TCP
  port, as Modbus TCP's. A serial port is one process's at a time whatever the unit or
  address on the bus (the drivers also open it exclusively), so the lock is the port's.

The lock files live in the runtime directory (:func:`runtime_directory`), which every
loopcal process on the host must agree on: ``$LOOPCAL_RUNTIME_DIR`` if set, else
``/run/loopcal`` if it exists (the service's ``RuntimeDirectory=``), else
``$XDG_RUNTIME_DIR/loopcal``, else a directory of the user's in the system's temporary
directory.
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import ipaddress
import json
import os
import re
import socket
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from loopcal.drivers import driver_for_url
from loopcal.drivers.url import device_server

from ..times import time_text

#: the environment variable that names the runtime directory (tests, unusual hosts)
RUNTIME_ENV = "LOOPCAL_RUNTIME_DIR"
#: the service's runtime directory (``RuntimeDirectory=loopcal`` in loopcal.service)
SYSTEM_RUNTIME_DIR = Path("/run/loopcal")
#: the most of a lock file read back to name its holder, bytes
_MAX_HOLDER_BYTES = 4096


def runtime_directory() -> Path:
    """Where the lock files and the daemon's control socket live (module docstring)."""
    env = os.environ.get(RUNTIME_ENV)
    if env:
        return Path(env)
    if SYSTEM_RUNTIME_DIR.is_dir():
        return SYSTEM_RUNTIME_DIR
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    if xdg:
        return Path(xdg) / "loopcal"
    return Path(tempfile.gettempdir()) / f"loopcal-{os.getuid()}"


def _address(host: str, port: int) -> str:
    """The address a host name reaches (loopback as one), or the name if it resolves not."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError):
        return host.lower()
    addrs = []
    for *_, sockaddr in infos:
        ip = ipaddress.ip_address(str(sockaddr[0]).split("%", 1)[0])
        if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        if ip.is_loopback:
            return "loopback"
        addrs.append(ip)
    if not addrs:
        return host.lower()
    # the first IPv4 address, as a client would most often connect to it
    return str(min(addrs, key=lambda a: (a.version, int(a))))


def module_key(url: str) -> str:
    """The module a driver URL reaches from this host, as a text two URLs share exactly
    when they reach the same module (module docstring).

    Parameters
    ----------
    url : str
        A driver URL (``modbus-tcp://...``, ``modbus-rtu:///dev/...``, ``ascii:///dev/...``,
        or a serial device server's ``modbus-rtu://HOST:PORT``, ``ascii://HOST:PORT``).

    Returns
    -------
    str
        ``"modbus-tcp ADDRESS:PORT unit N"``, ``"serial DEVICE"`` or, for a line behind a
        device server, ``"serial-tcp ADDRESS:PORT"`` (whatever the scheme, unit or address).

    Raises
    ------
    ValueError
        For a URL no driver takes (naming the problem, as :func:`loopcal.drivers.open_daq`).
    """
    cls, parsed = driver_for_url(url)
    options = cls.url_options(parsed)
    host = options.get("host")
    if isinstance(host, str):
        port = int(options["port"])  # type: ignore[call-overload]
        return f"{parsed.scheme} {_address(host, port)}:{port} unit {options.get('unit', 1)}"
    device = str(options["port"])
    server = device_server(device)
    if server is not None:
        return f"serial-tcp {_address(*server)}:{server[1]}"
    return f"serial {os.path.realpath(device) if device.startswith('/') else device}"


def lock_path(key: str, directory: Path | None = None) -> Path:
    """The lock file of the module ``key`` (:func:`module_key`): a readable name and a
    hash of the key, in ``directory`` (default :func:`runtime_directory`)."""
    readable = re.sub(r"[^A-Za-z0-9.-]+", "_", key).strip("_")[:60]
    digest = hashlib.sha256(key.encode()).hexdigest()[:12]
    return (directory or runtime_directory()) / f"module-{readable}-{digest}.lock"


@dataclass(frozen=True)
class Holder:
    """Who holds a module's lock, as its lock file says.

    pid: the holder's process id (0: unknown). command: how it was started. service: it
    is ``loopcal daemon`` (the service). url: the URL it records. since_ns: when it took
    the lock, ns since the Unix epoch (0: unknown).
    """

    pid: int = 0
    command: str = ""
    service: bool = False
    url: str = ""
    since_ns: int = 0

    @classmethod
    def read(cls, fd: int) -> Holder:
        """The holder a lock file names: unknown for an unreadable or half-written file, or
        one that names a process no longer alive (the holder could not write the file, an
        earlier holder's words stayed)."""
        try:
            doc = json.loads(os.pread(fd, _MAX_HOLDER_BYTES, 0).decode("utf-8"))
            holder = cls(int(doc["pid"]), str(doc.get("command", "")),
                         bool(doc.get("service")), str(doc.get("url", "")),
                         int(doc.get("since_ns", 0)))  # fmt: skip
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return cls()
        if holder.pid <= 0:
            return cls()
        try:
            os.kill(holder.pid, 0)
        except ProcessLookupError:
            return cls()
        except (PermissionError, OverflowError, ValueError):
            pass  # alive, another user's (or a pid no process can have: kept as written)
        return holder

    def describe(self) -> str:
        """``the loopcal service (pid 123, ...)`` or ``another loopcal process (pid 123:
        `loopcal record ...`)``."""
        who = "the loopcal service" if self.service else "another loopcal process"
        facts = [f"pid {self.pid}" if self.pid else "pid unknown"]
        if self.command:
            facts.append(f"`{self.command}`")
        if self.since_ns:
            facts.append("since " + time_text(self.since_ns))
        return f"{who} ({', '.join(facts)})"


class ModuleHeld(Exception):
    """The module is held by another loopcal process on this host (or its lock cannot be
    taken): the message names the holder and what to do instead."""

    def __init__(self, message: str, holder: Holder | None = None) -> None:
        super().__init__(message)
        self.holder = holder


def _advice(holder: Holder) -> str:
    if holder.service:
        m = re.search(r"--config[= ](\S+)", holder.command)
        config = m.group(1) if m else "/etc/loopcal/daemon.toml"
        return ("two readers would split its scans between them. To calibrate while the "
                f"service runs, use `loopcal session --config {config} --until-enough` "
                "(docs/calibration.md); to record it yourself, stop the service first "
                "(`systemctl stop loopcal`)")  # fmt: skip
    return ("two readers would split its scans between them. Stop that process first, or, "
            "if it is a daemon, work through it with `loopcal session` "
            "(docs/calibration.md)")  # fmt: skip


class ModuleLock:
    """The lock that makes this process the one owner of a module on the host.

    Parameters
    ----------
    url : str
        The driver URL about to be opened.
    command : str
        How this process was started (written into the lock file for the next one).
    service : bool
        This process is ``loopcal daemon``.
    directory : Path or None
        Where the lock files are (default :func:`runtime_directory`; created if missing).

    Raises
    ------
    ModuleHeld
        If another process holds the module (naming it), or the lock cannot be taken
        (the runtime directory cannot be made or the lock file not opened: the message
        says which, and how to fix it).
    ValueError
        For a URL no driver takes.
    """

    def __init__(self, url: str, *, command: str, service: bool = False,
                 directory: Path | None = None) -> None:  # fmt: skip
        self.url = url
        self.key = module_key(url)
        self.path = lock_path(self.key, directory)
        self._fd: int | None = None
        fd = self._open()
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                os.close(fd)
                raise ModuleHeld(f"cannot lock {self.path} for {url}: {exc.strerror}") from None
            holder = Holder.read(fd)
            os.close(fd)
            what = f" ({holder.url})" if holder.url and holder.url != url else ""
            raise ModuleHeld(
                f"the module at {url}{what} is already recorded by {holder.describe()}: "
                + _advice(holder), holder) from None  # fmt: skip
        self._fd = fd
        me = {"pid": os.getpid(), "command": command, "service": service, "url": url,
              "key": self.key, "since_ns": time.time_ns()}  # fmt: skip
        try:  # the file may be read-only to us (another user's): it is then unnamed
            os.ftruncate(fd, 0)
            os.pwrite(fd, (json.dumps(me) + "\n").encode(), 0)
        except OSError:
            pass

    def _open(self) -> int:
        directory = self.path.parent
        try:
            directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ModuleHeld(
                f"cannot make the runtime directory {directory} for the module's lock: "
                f"{exc.strerror}; set {RUNTIME_ENV} to a directory every loopcal process of "
                "this host can use") from None  # fmt: skip
        flags = os.O_CLOEXEC | os.O_NOFOLLOW
        try:
            return os.open(self.path, os.O_RDWR | os.O_CREAT | flags, 0o664)
        except PermissionError:
            try:  # another user's lock file (the service's): flock works read-only too
                return os.open(self.path, os.O_RDONLY | flags)
            except OSError as exc:
                why = exc.strerror
        except OSError as exc:
            why = exc.strerror
        raise ModuleHeld(
            f"cannot open the module's lock file {self.path}: {why}; the service's runtime "
            "directory is the loopcal group's (add your user to it), or set "
            f"{RUNTIME_ENV}") from None  # fmt: skip

    @property
    def held(self) -> bool:
        """Whether this object still holds the lock."""
        return self._fd is not None

    def release(self) -> None:
        """Give the lock up (the process's end does it too). The file stays."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)

    def __del__(self) -> None:
        self.release()

    def __enter__(self) -> ModuleLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"ModuleLock({self.key!r}, {str(self.path)!r}, held={self.held})"
