"""The systemd notify protocol (sd_notify(3)): READY, STATUS, WATCHDOG over a datagram.

systemd passes a unix datagram socket in ``$NOTIFY_SOCKET`` (a path, or ``@name`` for the
abstract namespace) to a ``Type=notify`` service; each message is one datagram of
``KEY=value`` lines. With ``WatchdogSec=``, ``$WATCHDOG_USEC`` says how often the service
must send ``WATCHDOG=1`` (we send twice as often), and ``$WATCHDOG_PID``, if set, which
process it means. Outside systemd every call is a no-op, so the same code runs anywhere.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from collections.abc import Mapping

log = logging.getLogger("daemon.sdnotify")

MAX_STATUS = 1000


class Notifier:
    """Send sd_notify(3) messages to ``$NOTIFY_SOCKET``. A no-op when not run by systemd.

    socket_path: the socket (None: ``NOTIFY_SOCKET`` from ``environ``, default os.environ).
    """

    def __init__(
        self, socket_path: str | None = None, *, environ: Mapping[str, str] | None = None
    ) -> None:
        env = os.environ if environ is None else environ
        path = socket_path if socket_path is not None else env.get("NOTIFY_SOCKET", "")
        self._address = "\0" + path[1:] if path.startswith("@") else path
        self._sock: socket.socket | None = None
        self._warned = False
        self._watchdog = _watchdog_interval(env)

    @property
    def enabled(self) -> bool:
        return bool(self._address)

    @property
    def watchdog_interval(self) -> float | None:
        """Seconds between WATCHDOG=1 pings (half of WATCHDOG_USEC), or None."""
        return self._watchdog

    def send(self, **fields: str | int) -> bool:
        """One datagram of ``KEY=value`` lines; False if disabled or it could not be sent."""
        if not self._address:
            return False
        text = "\n".join(f"{k}={str(v).replace(chr(10), ' ')}" for k, v in fields.items())
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(text.encode("utf-8", "replace"), self._address)
        except OSError as exc:
            if not self._warned:
                self._warned = True
                log.warning("cannot notify systemd at %r: %s", self._address, exc)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.send(READY=1, **_status(status))

    def status(self, text: str) -> bool:
        return self.send(STATUS=text[:MAX_STATUS])

    def watchdog(self) -> bool:
        return self.send(WATCHDOG=1)

    def reloading(self) -> bool:
        """RELOADING=1 with the CLOCK_MONOTONIC time, as ``Type=notify-reload`` wants."""
        return self.send(RELOADING=1, MONOTONIC_USEC=time.monotonic_ns() // 1000)

    def stopping(self, status: str | None = None) -> bool:
        return self.send(STOPPING=1, **_status(status))

    def close(self) -> None:
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
