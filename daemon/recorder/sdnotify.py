"""The systemd notify protocol (sd_notify(3)): READY, STATUS, WATCHDOG over a datagram.

systemd passes a unix datagram socket in ``$NOTIFY_SOCKET`` (an absolute path, or ``@name``
for the abstract namespace) to a ``Type=notify`` service; each message is one datagram of
``KEY=value`` lines. With ``WatchdogSec=``, ``$WATCHDOG_USEC`` says how often the service
must send ``WATCHDOG=1`` (we send twice as often), and ``$WATCHDOG_PID``, if set, which
process it means. Outside systemd every call is a no-op, so the same code runs anywhere.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Mapping

log = logging.getLogger(__name__)

MAX_STATUS = 1000  # characters of STATUS= kept; systemctl status shows one line anyway


class Notifier:
    """Send sd_notify(3) messages to ``$NOTIFY_SOCKET``. A no-op when not run by systemd.

    socket_path: the notify socket, an absolute path or ``@name`` (abstract namespace);
    None: ``NOTIFY_SOCKET`` from ``environ`` (default ``os.environ``). Absent, empty or any
    other form (systemd itself only hands out those two): disabled. ``WATCHDOG_USEC`` and
    ``WATCHDOG_PID`` are read from ``environ`` too. Safe to use from several threads.
    """

    def __init__(
        self, socket_path: str | None = None, *, environ: Mapping[str, str] | None = None
    ) -> None:
        env = os.environ if environ is None else environ
        path = socket_path if socket_path is not None else env.get("NOTIFY_SOCKET", "")
        self._address = ""
        if path.startswith("@") and len(path) > 1:
            self._address = "\0" + path[1:]
        elif path.startswith("/"):
            self._address = path
        elif path:
            log.warning("ignoring NOTIFY_SOCKET=%r: neither an absolute path nor @name", path)
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._warned = False
        self._watchdog = _watchdog_interval(env) if self._address else None

    @property
    def enabled(self) -> bool:
        """True when there is a notify socket to send to."""
        return bool(self._address)

    @property
    def watchdog_interval(self) -> float | None:
        """Seconds between WATCHDOG=1 pings (half of WATCHDOG_USEC), or None when systemd
        watches no watchdog for this process (or WATCHDOG_USEC/WATCHDOG_PID is malformed)."""
        return self._watchdog

    def send(self, **fields: str | int) -> bool:
        """Send ``fields`` as one datagram of ``KEY=value`` lines, keys as given.

        Newlines in values become spaces (a newline ends a field). Never blocks and never
        raises: returns False if disabled or the datagram could not be sent (the first such
        failure is logged as a warning).
        """
        if not self._address:
            return False
        text = "\n".join(f"{k}={str(v).replace(chr(10), ' ')}" for k, v in fields.items())
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(
                        socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC
                    )
                # MSG_DONTWAIT: a manager that does not read its queue must not stall the
                # caller (the acquisition loop feeds the watchdog); that message is lost.
                self._sock.sendto(
                    text.encode("utf-8", "replace"), socket.MSG_DONTWAIT, self._address
                )
            except OSError as exc:
                if not self._warned:
                    self._warned = True
                    where = "@" + self._address[1:] if self._address[0] == "\0" else self._address
                    log.warning("cannot notify systemd at %r: %s", where, exc)
                return False
        return True

    def ready(self, status: str | None = None) -> bool:
        """READY=1: startup (or a reload) is complete; with STATUS= if ``status`` is given."""
        return self.send(READY=1, **_status(status))

    def status(self, text: str) -> bool:
        """STATUS=: the one-line state ``systemctl status`` shows (cut to MAX_STATUS)."""
        return self.send(STATUS=text[:MAX_STATUS])

    def watchdog(self) -> bool:
        """WATCHDOG=1: keep-alive; send every :attr:`watchdog_interval` seconds."""
        return self.send(WATCHDOG=1)

    def reloading(self) -> bool:
        """RELOADING=1 with MONOTONIC_USEC= (CLOCK_MONOTONIC, µs), as ``Type=notify-reload``
        requires; send READY=1 when the reload is done."""
        return self.send(RELOADING=1, MONOTONIC_USEC=time.monotonic_ns() // 1000)

    def stopping(self, status: str | None = None) -> bool:
        """STOPPING=1: shutdown has begun; with STATUS= if ``status`` is given."""
        return self.send(STOPPING=1, **_status(status))

    def close(self) -> None:
        """Close the socket (idempotent; a later send opens a new one)."""
        with self._lock:
            if self._sock is not None:
                self._sock.close()
                self._sock = None


def _status(text: str | None) -> dict[str, str]:
    return {} if text is None else {"STATUS": text[:MAX_STATUS]}


def _watchdog_interval(env: Mapping[str, str]) -> float | None:
    usec = env.get("WATCHDOG_USEC", "")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID", "")
    try:
        if pid and int(pid) != os.getpid():
            return None
        value = int(usec)
    except ValueError:
        log.warning("ignoring malformed WATCHDOG_USEC=%r / WATCHDOG_PID=%r", usec, pid)
        return None
    return value / 2e6 if value > 0 else None
