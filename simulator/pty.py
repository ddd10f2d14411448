"""A null-modem cable made of two pseudo-terminals, like ``socat pty,raw pty,raw``.

The module's server opens one slave (:attr:`PtyLink.device_path`), the driver opens the
other (:attr:`PtyLink.host_path`) with pyserial exactly as it would open /dev/ttyUSB0,
and a relay on the emulator's asyncio loop copies bytes between the two masters. The
relay is where a cut cable is modeled: while ``connected()`` is false, bytes in both
directions are lost.

The link keeps both slaves open itself, so a master never sees EIO when the driver
closes and reopens its port, and sets them raw at creation (no echo, no CR/LF mapping)
so nothing written before the driver opens its port is mangled by the line discipline.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty
from collections.abc import Callable

_CHUNK = 4096


class PtyPair:
    """One pseudo-terminal: master fd (non-blocking), raw slave fd and the slave's path.

    Attributes
    ----------
    master : int
        The master's file descriptor, non-blocking.
    slave : int
        The slave's file descriptor, set raw (no echo, no CR/LF mapping).
    path : str
        The slave's path, e.g. ``/dev/pts/7``.

    Raises
    ------
    OSError
        If no pseudo-terminal can be opened.
    """

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)

    def close(self) -> None:
        """Close both file descriptors (errors ignored: closing twice is harmless)."""
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class PtyLink:
    """Two pty pairs joined by a relay running on an asyncio loop: a null-modem cable.

    Attributes
    ----------
    bytes_to_device : int
        Bytes relayed from the driver's side to the module's (diagnostics).
    bytes_to_host : int
        Bytes relayed from the module's side to the driver's.

    Raises
    ------
    OSError
        If the two pseudo-terminals cannot be opened (none is left open then).
    """

    def __init__(self) -> None:
        self._device = PtyPair()
        try:
            self._host = PtyPair()
        except OSError:
            self._device.close()
            raise
        self._loop: asyncio.AbstractEventLoop | None = None
        self._connected: Callable[[], bool] = lambda: True
        self.bytes_to_device = 0
        self.bytes_to_host = 0

    @property
    def device_path(self) -> str:
        """The slave the module's server opens."""
        return self._device.path

    @property
    def device_fd(self) -> int:
        """The module side's slave fd (raw, blocking), for servers that use the fd."""
        return self._device.slave

    @property
    def host_path(self) -> str:
        """The slave the driver opens, e.g. ``/dev/pts/7``."""
        return self._host.path

    def start(self, loop: asyncio.AbstractEventLoop, connected: Callable[[], bool]) -> None:
        """Start relaying on ``loop`` (call from the loop's thread).

        Parameters
        ----------
        loop : asyncio.AbstractEventLoop
            The loop whose readers copy the bytes.
        connected : callable
            ``connected() -> bool``, asked for each chunk: while it is False, bytes in both
            directions are lost (a cut cable).
        """
        self._loop = loop
        self._connected = connected
        loop.add_reader(self._host.master, self._relay, self._host.master, self._device.master)
        loop.add_reader(self._device.master, self._relay, self._device.master, self._host.master)

    def _relay(self, src: int, dst: int) -> None:
        try:
            data = os.read(src, _CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return
        if not data or not self._connected():
            return
        if dst == self._device.master:
            self.bytes_to_device += len(data)
        else:
            self.bytes_to_host += len(data)
        view = memoryview(data)
        while view:
            try:
                view = view[os.write(dst, view) :]
            except (BlockingIOError, InterruptedError):
                return  # the other side's input buffer is full: a real line overruns too
            except OSError:
                return

    def close(self) -> None:
        """Stop relaying (from the loop's thread) and close every fd."""
        if self._loop is not None:
            for fd in (self._host.master, self._device.master):
                with contextlib.suppress(Exception):
                    self._loop.remove_reader(fd)
            self._loop = None
        self._host.close()
        self._device.close()
