"""How many bytes wait on a serial line, whatever carries it: :func:`bytes_waiting`.

pyserial's ``in_waiting`` of a ``socket://`` line (a serial device server's TCP port,
:mod:`loopcal.drivers.url`) says only whether a byte waits: 0 or 1. pymodbus' serial
client reads what is waiting and looks again a millisecond later, so it took a 245-byte
FIFO answer a byte at a time, in half a second, past a 0.25 s timeout. The socket itself
knows the count (``FIONREAD``), as a tty does.
"""

from __future__ import annotations

import array
import fcntl
import socket
import termios

import serial


def bytes_waiting(line: serial.SerialBase) -> int:
    """Bytes received on ``line`` and not read yet.

    Parameters
    ----------
    line : serial.SerialBase
        An open pyserial port: a serial device, or a ``socket://`` line.

    Returns
    -------
    int
        The count (a socket line's own, where pyserial's ``in_waiting`` says 0 or 1).

    Raises
    ------
    OSError
        If the line has failed (pyserial's SerialException is one).
    """
    sock = getattr(line, "_socket", None)  # where pyserial's socket:// handler keeps it
    if isinstance(sock, socket.socket):
        count = array.array("i", [0])
        fcntl.ioctl(sock.fileno(), termios.FIONREAD, count)
        return count[0]
    return line.in_waiting


__all__ = ["bytes_waiting"]
