"""The daemon's control protocol: what ``loopcal session`` and the daemon say to each other
over the daemon's control socket (a unix stream socket, ``[control].socket``).

Each message is one JSON object on one line (UTF-8, ``\\n``-terminated), at most
:data:`MAX_MESSAGE_BYTES`. The client sends requests, ``{"request": NAME, ...}``; the
daemon sends replies and stream messages, ``{"type": NAME, ...}``. The requests are the
few a session needs, and nothing else (no config change, no file path from a client):

``start``
    ``note`` (text, at most :data:`MAX_NOTE_CHARS`), ``target_mm`` (0 < x <= 10),
    ``until_enough`` (bool), ``duration_s`` (null or 0 < x <= :data:`MAX_DURATION_S`),
    ``free`` (null or a free set, as ``--free`` takes it). The connection that starts a
    session owns it: it is streamed the guidance (``{"type": "guidance", "update":
    {...}, "lines": [...]}``: the update as ``record --until-enough --json`` prints it, and
    the lines of its display), may stop it, and must say something at least every ``[control].
    client_timeout`` (a ``status`` does), else the session ends as abandoned. Reply:
    ``started`` (``session``: its description), or ``error``.
``status``
    Reply ``status``: the session running (or null) and the recorder's status line.
``stream``
    Follow the running session's guidance without owning it (a second terminal). Reply
    ``streaming``, then its guidance and its end.
``stop``
    End the session this connection started. Its end follows.

When a session ends, every connection that follows it gets ``{"type": "ended",
"session": ...}`` once the daemon has written its scans to disk (``flushed``), with the
window of the recording it covers (``since_ns``, ``until_ns``: the stamps of its first and
last scan) and why it ended (``reason``: enough, duration, stopped, abandoned, daemon
stopping). A message that is not one of these gets ``{"type": "error", "error": TEXT}``
naming what is wrong; one longer than :data:`MAX_MESSAGE_BYTES` closes the connection.

:func:`parse_request` checks a request; :func:`bind_control_socket` is the daemon's end
(the server is :class:`loopcal.daemon.live.sessions.ControlServer`), :class:`ControlClient`
the client's.
"""

from __future__ import annotations

import errno
import json
import math
import os
import pwd
import socket
import stat
import struct
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .guidance_defaults import MAX_TARGET_MM

#: the longest message either side may send, bytes (a guidance update is about 1.5 KB)
MAX_MESSAGE_BYTES = 16384
#: the longest note a session may carry, characters
MAX_NOTE_CHARS = 500
#: the longest session a client may ask for, s
MAX_DURATION_S = 4 * 3600.0
#: the requests the daemon takes, and the fields each may carry
REQUESTS: dict[str, frozenset[str]] = {
    "start": frozenset({"note", "target_mm", "until_enough", "duration_s", "free"}),
    "status": frozenset(),
    "stream": frozenset(),
    "stop": frozenset(),
}


class ProtocolError(ValueError):
    """A message that breaks the protocol: the text names what is wrong."""


class ControlError(Exception):
    """The control socket cannot be reached or used: the text says why and what to do."""


@dataclass(frozen=True)
class StartRequest:
    """A checked ``start`` request (module docstring)."""

    note: str = ""
    target_mm: float = 0.1
    until_enough: bool = False
    duration_s: float | None = None
    free: str | None = None


def encode(message: dict[str, Any]) -> bytes:
    """One message as its line of JSON (no NaN: ``null``)."""
    return (json.dumps(message, allow_nan=False, separators=(",", ":"),
                       default=_plain) + "\n").encode("utf-8")  # fmt: skip


def _plain(obj: Any) -> Any:
    if hasattr(obj, "item"):  # numpy scalars
        return obj.item()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def decode(line: bytes) -> dict[str, Any]:
    """One line of the protocol as a JSON object.

    Raises
    ------
    ProtocolError
        If it is too long, not UTF-8, not JSON, or not an object.
    """
    if len(line) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"a message of more than {MAX_MESSAGE_BYTES} bytes")
    try:
        obj = json.loads(line.decode("utf-8"), parse_constant=_no_constant)
    except UnicodeDecodeError:
        raise ProtocolError("not UTF-8 text") from None
    except (ValueError, RecursionError) as exc:
        raise ProtocolError(f"not JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise ProtocolError(f"not a JSON object but {type(obj).__name__}")
    return obj


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a number JSON allows")


def parse_request(line: bytes) -> tuple[str, StartRequest | None]:
    """A client's line as ``(request name, StartRequest or None)``.

    Raises
    ------
    ProtocolError
        Naming what is wrong: the message, an unknown request (naming those there are),
        an unknown field, or a field's value.
    """
    msg = decode(line)
    name = msg.get("request")
    if not isinstance(name, str) or name not in REQUESTS:
        raise ProtocolError(f"unknown request {name!r} (the requests: "
                            f"{', '.join(REQUESTS)})")  # fmt: skip
    extra = set(msg) - {"request"} - REQUESTS[name]
    if extra:
        raise ProtocolError(f"{name}: unknown field(s) {', '.join(sorted(map(repr, extra)))}")
    if name != "start":
        return name, None
    return name, _start(msg)


def _start(msg: dict[str, Any]) -> StartRequest:
    note = msg.get("note", "")
    if not isinstance(note, str) or len(note) > MAX_NOTE_CHARS:
        raise ProtocolError(f"start: note must be a text of at most {MAX_NOTE_CHARS} "
                            "characters")  # fmt: skip
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in note):
        raise ProtocolError("start: note has control characters")
    target = _number(msg, "target_mm", 0.1)
    if not 0 < target <= MAX_TARGET_MM:
        raise ProtocolError(f"start: target_mm must be > 0 and <= {MAX_TARGET_MM:g} mm")
    until = msg.get("until_enough", False)
    if not isinstance(until, bool):
        raise ProtocolError("start: until_enough must be true or false")
    duration = msg.get("duration_s")
    if duration is not None:
        duration = _number(msg, "duration_s", 0.0)
        if not 0 < duration <= MAX_DURATION_S:
            raise ProtocolError(f"start: duration_s must be > 0 and <= {MAX_DURATION_S:g} s")
    free = msg.get("free")
    if free is not None and (not isinstance(free, str) or not 0 < len(free) <= 200):
        raise ProtocolError("start: free must be a free set, as --free takes it")
    return StartRequest(note, target, until, duration, free)


def _number(msg: dict[str, Any], key: str, default: float) -> float:
    value = msg.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ProtocolError(f"start: {key} must be a number")
    return float(value)


def peer_of(sock: socket.socket) -> dict[str, Any]:
    """Who is on the other end of a unix socket (Linux's SO_PEERCRED)."""
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
        pid, uid, gid = struct.unpack("3i", raw)
    except (OSError, AttributeError):
        return {"user": "unknown"}
    try:
        user = pwd.getpwuid(uid).pw_name
    except KeyError:
        user = str(uid)
    return {"user": user, "uid": uid, "pid": pid}


#: connections the kernel queues before the control thread accepts them (a burst of clients
#: on a loaded controller waits there rather than being turned away)
BACKLOG = 64


def bind_control_socket(path: Path) -> socket.socket:
    """Listen on the unix socket ``path``, owner and group only (0660).

    A socket file left by a daemon that died is replaced; a live one is refused.

    Raises
    ------
    ControlError
        If another daemon listens there, something else is in the way, or the socket
        cannot be made (naming the path and the reason).
    """
    if os.path.lexists(path):
        mode = os.lstat(path).st_mode
        if not stat.S_ISSOCK(mode):
            raise ControlError(f"[control].socket {path}: exists and is not a socket")
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            probe.connect(str(path))
        except OSError:
            os.unlink(path)  # nobody listens: a dead daemon's
        else:
            raise ControlError(f"[control].socket {path}: another loopcal daemon listens "
                               "there; give each daemon a socket of its own")  # fmt: skip
        finally:
            probe.close()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.bind(str(path))
        os.chmod(path, 0o660)
        sock.listen(BACKLOG)
    except OSError as exc:
        raise ControlError(f"[control].socket {path}: cannot listen there: "
                           f"{exc.strerror or exc}") from None  # fmt: skip
    sock.setblocking(False)
    return sock


def connect_error(path: Path, exc: OSError) -> ControlError:
    """What a failed connection to the control socket at ``path`` means, in words."""
    if exc.errno in (errno.ENOENT, errno.ECONNREFUSED):
        return ControlError(
            f"no loopcal daemon answers at {path} (is the service running? "
            "`systemctl status loopcal`). Without the service, record and calibrate in one "
            "go: `loopcal record --daq URL --out DIR --controller-config PATH --until-enough`, "
            "then `loopcal calibrate DIR --controller-config PATH --write`")  # fmt: skip
    if exc.errno in (errno.EACCES, errno.EPERM):
        return ControlError(
            f"permission denied on the daemon's control socket {path}: your user must be in "
            "the loopcal group (`usermod -aG loopcal USER`, then log in again)")  # fmt: skip
    return ControlError(f"cannot connect to the daemon's control socket {path}: "
                        f"{exc.strerror or exc}")  # fmt: skip


class ControlClient:
    """The client's end of the control socket: send requests, receive messages.

    Parameters
    ----------
    path : Path
        The daemon's control socket.
    timeout : float
        s to wait for the connection.

    Raises
    ------
    ControlError
        If no daemon answers there, or the socket cannot be used (:func:`connect_error`).
    """

    def __init__(self, path: Path, *, timeout: float = 5.0) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.settimeout(timeout)
        try:
            self.sock.connect(str(path))
        except OSError as exc:
            self.sock.close()
            raise connect_error(path, exc) from None
        self._buffer = b""

    def send(self, request: str, **fields: Any) -> None:
        """Send one request (:data:`REQUESTS`).

        Raises
        ------
        ControlError
            If the daemon has gone.
        """
        try:
            self.sock.sendall(encode({"request": request, **fields}))
        except OSError as exc:
            raise ControlError(f"the daemon closed its control socket {self.path}: "
                               f"{exc.strerror or exc}") from None  # fmt: skip

    def receive(self, timeout: float | None) -> dict[str, Any] | None:
        """The next message, or None if none came within ``timeout`` s.

        Raises
        ------
        ControlError
            If the daemon closed the connection, or sent what is not the protocol.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while b"\n" not in self._buffer:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                return None
            self.sock.settimeout(left)
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                return None
            except OSError as exc:
                raise ControlError(f"the daemon's control socket {self.path} failed: "
                                   f"{exc.strerror or exc}") from None  # fmt: skip
            if not data:
                raise ControlError(f"the daemon closed its control socket {self.path}")
            self._buffer += data
            if len(self._buffer) > 4 * MAX_MESSAGE_BYTES and b"\n" not in self._buffer:
                raise ControlError("the daemon sent a message longer than the protocol allows")
        line, self._buffer = self._buffer.split(b"\n", 1)
        try:
            return decode(line)
        except ProtocolError as exc:
            raise ControlError(f"the daemon sent what is not the protocol: {exc}") from None

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
