"""The ASCII protocol server: reads CR-terminated frames from a serial fd and answers.

Runs on the emulator's asyncio loop. Each complete frame is answered at once (well within
the datasheet's 10 ms), or after the drawn latency (an open point: the answer is decided
when the frame arrives, sent later, answers in the order of their frames), unless the
module is off, stalled or the link is down, in which case the frame is silently lost, as
on the real module.

Decision where the datasheet is silent: the module's line buffer holds 64 bytes; a longer
run without CR is discarded (line noise cannot grow it without bound).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import Callable

from .ascii_protocol import handle_frame
from .handle import DeviceHandle
from .wire import corrupt_ascii

LINE_BUFFER_BYTES = 64


class AsciiServer:
    """Serve the ASCII protocol for module ``address`` on the (raw) serial fd ``fd``, or
    on a byte stream that calls :meth:`feed` (``fd`` -1 and a ``send``).

    Parameters
    ----------
    handle : DeviceHandle
        The device, clock and wire faults, behind their lock.
    fd : int
        The module side of the serial line (a pty slave,
        :attr:`~loopcal.simulator.pty.PtyLink.device_fd`); made non-blocking by
        :meth:`start`. -1: no fd, the bytes come through :meth:`feed`.
    address : int
        The module address, 0..255 (``AA`` in the frames, two uppercase hex digits).
    send : callable or None, default None
        ``send(bytes)`` puts an answer on the line (a TCP connection's write, for a line
        behind a serial device server: :mod:`loopcal.simulator.device_server`); None: the
        fd.

    Attributes
    ----------
    handle : DeviceHandle
        As given.
    fd : int
        As given.
    address : int
        As given.

    Raises
    ------
    ValueError
        If ``address`` is outside 0..255, or neither an fd nor ``send`` is given.
    """

    def __init__(
        self, handle: DeviceHandle, fd: int, address: int,
        send: Callable[[bytes], None] | None = None,
    ) -> None:  # fmt: skip
        if not 0 <= address <= 0xFF:
            raise ValueError("ASCII address must be 0..255")
        if fd < 0 and send is None:
            raise ValueError("an ASCII server needs an fd or a send callable")
        self.handle = handle
        self.fd = fd
        self.address = address
        self._send = send if send is not None else self._write
        self._buffer = bytearray()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._send_at = 0.0  # loop time the latest delayed answer goes out

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Answer frames as they arrive on ``loop`` (call from the loop's thread).

        Parameters
        ----------
        loop : asyncio.AbstractEventLoop
            The emulator's loop: it reads the fd (if any) and sends delayed answers.
        """
        self._loop = loop
        if self.fd >= 0:
            os.set_blocking(self.fd, False)
            loop.add_reader(self.fd, self._on_readable)

    def _on_readable(self) -> None:
        try:
            data = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return
        self.feed(data)

    def feed(self, data: bytes) -> None:
        """Bytes the line carried to the module: answer each frame they complete.

        Parameters
        ----------
        data : bytes
            As received, any split (a frame may span calls).
        """
        self._buffer += data
        while (end := self._buffer.find(b"\r")) >= 0:
            frame = bytes(self._buffer[:end])
            del self._buffer[: end + 1]
            self._answer(frame)
        if len(self._buffer) > LINE_BUFFER_BYTES:
            self._buffer.clear()

    def _answer(self, frame: bytes) -> None:
        self.handle.note_request()
        with self.handle.synced() as device:
            if not self.handle.responsive_locked():
                return
            answer = handle_frame(device, frame, self.address)
            if answer is None:
                return
            out = self.handle.wire.outgoing(answer, corrupt_ascii(device.ascii_checksum))
            delay = self.handle.wire.delay_s("ascii")
        if delay > 0 and self._loop is not None:
            self._send_at = max(self._loop.time() + delay, self._send_at)
            self._loop.call_at(self._send_at, self._send, out)
            return
        self._send(out)

    def _write(self, out: bytes) -> None:
        view = memoryview(out)
        while view:
            try:
                view = view[os.write(self.fd, view) :]
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return

    def close(self) -> None:
        """Stop reading the fd (the fd itself belongs to the pty link, which closes it)."""
        if self._loop is not None:
            if self.fd >= 0:
                with contextlib.suppress(Exception):
                    self._loop.remove_reader(self.fd)
            self._loop = None
