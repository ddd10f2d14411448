"""A null-modem cable made of two pseudo-terminals, like ``socat pty,raw pty,raw``.

The module's server opens one slave (:attr:`PtyLink.device_path`), the driver opens the
other (:attr:`PtyLink.host_path`) with pyserial exactly as it would open /dev/ttyUSB0,
and a relay on the emulator's asyncio loop copies bytes between the two masters. The
relay is where a cut cable is modeled: while ``connected()`` is false, bytes in both
directions are lost.

The link keeps both slaves open itself, so a master never sees EIO when the driver
closes and reopens its port, and sets them raw at creation (no echo, no CR/LF mapping)
so nothing written before the driver opens its port is mangled by the line discipline.

The relay also models the line's rate. A pty carries no signal, but it keeps the speed
each side set (a master's ``tcgetattr`` shows its slave's settings on Linux): the module's
side is set to the module's configured rate (:attr:`PtyLink.baud`), and the driver's
side to whatever the driver opened it with. When the two differ, each byte is passed
through :func:`~loopcal.simulator.wire.uart_receive`, as a UART at the wrong rate would
read it: the module hears garbage and, finding no valid frame, does not answer, and
anything it sends reaches the host as garbage too. Parity is not modeled: Linux's pty
driver forces 8 data bits and no parity whatever the side asks for, so a pty cannot tell
which parity a side set.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import os
import struct
import termios
import tty
from collections.abc import Callable

from loopcal.drivers.ldq412 import SERIAL_BAUD

from .wire import uart_receive

_CHUNK = 4096
#: termios speed constant -> baud, for the rates the termios module names
_SPEEDS = {getattr(termios, f"B{rate}"): rate for rate in (
    50, 75, 110, 134, 150, 200, 300, 600, 1200, 1800, 2400, 4800, 9600, 19200, 38400, 57600,
    115200, 230400, 460800, 500000, 576000, 921600, 1000000, 1152000, 1500000, 2000000,
    2500000, 3000000, 3500000, 4000000) if hasattr(termios, f"B{rate}")}  # fmt: skip
#: Linux's "another rate" speed (BOTHER): the rate itself is in struct termios2 (TCGETS2)
_BOTHER = 0o010000
_TCGETS2 = 0x802C542A
_TERMIOS2 = struct.Struct("4IB19B2I")  # flags, line discipline, c_cc, ispeed, ospeed


def tty_baud(fd: int) -> int | None:
    """The output rate a terminal is set to, baud: a slave's own, or through its master.

    Parameters
    ----------
    fd : int
        A terminal's file descriptor (a pty master shows its slave's settings).

    Returns
    -------
    int or None
        The rate; None if it cannot be read (a closed fd, a rate this system does not say).
    """
    try:
        speed = termios.tcgetattr(fd)[5]
        if speed != _BOTHER:
            return _SPEEDS.get(speed)
        buf = bytearray(_TERMIOS2.size)
        fcntl.ioctl(fd, _TCGETS2, buf)
        return _TERMIOS2.unpack(bytes(buf))[-1] or None
    except (OSError, termios.error):
        return None


def set_tty_baud(fd: int, baud: int) -> None:
    """Set a terminal's input and output rate (one that termios names, e.g. 115200).

    Parameters
    ----------
    fd : int
        The terminal's file descriptor.
    baud : int
        The rate, baud.

    Raises
    ------
    ValueError
        For a rate termios does not name.
    """
    speed = {rate: code for code, rate in _SPEEDS.items()}.get(baud)
    if speed is None:
        raise ValueError(f"{baud} baud is not a rate a pty can be set to here")
    attrs = termios.tcgetattr(fd)
    attrs[4] = attrs[5] = speed
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


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

    Parameters
    ----------
    baud : int, default 115200
        The rate the slave is set to (what a side that never sets one is at).

    Raises
    ------
    OSError
        If no pseudo-terminal can be opened.
    ValueError
        For a rate termios does not name.
    """

    def __init__(self, baud: int = SERIAL_BAUD) -> None:
        self.master, self.slave = os.openpty()
        try:
            tty.setraw(self.slave)
            set_tty_baud(self.slave, baud)
        except BaseException:
            self.close()
            raise
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)

    def close(self) -> None:
        """Close both file descriptors (errors ignored: closing twice is harmless)."""
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


class PtyLink:
    """Two pty pairs joined by a relay running on an asyncio loop: a null-modem cable.

    Parameters
    ----------
    baud : int, default 115200
        The module's configured rate, baud: its side's slave is set to it, and so is the
        driver's until the driver sets its own (module docstring: another rate garbles
        every byte).

    Attributes
    ----------
    baud : int
        As given.
    bytes_to_device : int
        Bytes relayed from the driver's side to the module's (diagnostics), as sent.
    bytes_to_host : int
        Bytes relayed from the module's side to the driver's, as sent.
    bytes_lost : int
        Bytes read from either side while the cable was cut (diagnostics).

    Raises
    ------
    OSError
        If the two pseudo-terminals cannot be opened (none is left open then).
    ValueError
        For a rate termios does not name.
    """

    def __init__(self, baud: int = SERIAL_BAUD) -> None:
        self.baud = baud
        self._device = PtyPair(baud)
        try:
            self._host = PtyPair(baud)
        except BaseException:
            self._device.close()
            raise
        self._loop: asyncio.AbstractEventLoop | None = None
        self._connected: Callable[[], bool] = lambda: True
        self.bytes_to_device = 0
        self.bytes_to_host = 0
        self.bytes_lost = 0

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
        if not data:
            return
        if not self._connected():
            self.bytes_lost += len(data)
            return
        if dst == self._device.master:
            self.bytes_to_device += len(data)
        else:
            self.bytes_to_host += len(data)
        sent, heard = tty_baud(src), tty_baud(dst)
        if sent is not None and heard is not None and sent != heard:
            data = uart_receive(data, sent, heard)
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
