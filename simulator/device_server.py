"""A serial device server in front of the module: its serial line reached over raw TCP.

In the field a module's RS-485 line is often reached through a serial device server (a
Moxa NPort in "TCP server" mode, say): it listens on a TCP port and passes the bytes of
each connection to the line and back, unchanged. The drivers reach such a line by a serial
URL with a host and a port (``modbus-rtu://HOST:PORT?unit=1``, ``ascii://HOST:PORT?addr=01``;
pyserial's ``socket://``). :class:`DeviceServer` is one on 127.0.0.1, with the module's
RTU or ASCII server behind it.

What it models, and what it leaves out:

- The device server stays up whatever the module does: a module powered off, stalled or
  behind a cut cable (:mod:`loopcal.simulator.faults`) leaves connections open and
  requests unanswered, as on the pseudo-terminal line.
- No line rate: the device server's serial side is set in the device server, so a driver's
  baud rate and parity (which pyserial ignores on a socket) change nothing.
- It accepts any number of connections, each a line of its own to the module (a real one
  is configured for one or a few; a second program is then refused or shares the line).

The emulator's tests of what the tty does (its rate, a port held by another program, a cut
cable's lost bytes) run on the pseudo-terminal line (:mod:`loopcal.simulator.pty`); this
one carries the bytes the way loopback TCP does, without the kernel's pty buffer work,
which a loaded machine can hold up for seconds.
"""

from __future__ import annotations

import asyncio

from pymodbus.framer import FramerType
from pymodbus.server import ModbusTcpServer

from .ascii_server import AsciiServer
from .handle import DeviceHandle
from .modbus_server import ModbusAdapter
from .wire import corrupt_rtu


class _AsciiConnection(asyncio.Protocol):
    """One TCP connection's line to the module's ASCII server."""

    def __init__(self, handle: DeviceHandle, address: int, open_: set[_AsciiConnection]) -> None:
        self._handle = handle
        self._address = address
        self._open = open_  # the device server's connections, closed with it
        self._server: AsciiServer | None = None
        self._transport: asyncio.Transport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport
        self._open.add(self)
        self._server = AsciiServer(self._handle, -1, self._address, send=self._send)
        self._server.start(asyncio.get_running_loop())

    def _send(self, out: bytes) -> None:
        if self._transport is not None and not self._transport.is_closing():
            self._transport.write(out)

    def data_received(self, data: bytes) -> None:
        if self._server is not None:
            self._server.feed(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self._open.discard(self)
        if self._server is not None:
            self._server.close()
        self._server = self._transport = None

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()


class DeviceServer:
    """A serial device server on ``host:port`` with the module's serial protocol behind it.

    Parameters
    ----------
    handle : DeviceHandle
        The device, clock and wire faults, behind their lock.
    transport : {"modbus-rtu", "ascii"}
        The protocol on the line: Modbus RTU frames (pymodbus' RTU framer on a TCP
        server) or the module's ASCII frames.
    unit : int
        The Modbus unit id (modbus-rtu).
    ascii_addr : int
        The ASCII module address, 0..255 (ascii).
    host : str, default "127.0.0.1"
        Listening address.
    port : int, default 0
        Listening port; 0: a free one, in :attr:`port` after :meth:`listen`.

    Attributes
    ----------
    transport, host : str
        As given.
    port : int
        The port listened on (after :meth:`listen`).
    """

    def __init__(
        self, handle: DeviceHandle, transport: str, *, unit: int, ascii_addr: int,
        host: str = "127.0.0.1", port: int = 0,
    ) -> None:  # fmt: skip
        if transport not in ("modbus-rtu", "ascii"):
            raise ValueError(f"a serial device server carries modbus-rtu or ascii, not "
                             f"{transport!r}")  # fmt: skip
        self.handle = handle
        self.transport = transport
        self.unit = unit
        self.ascii_addr = ascii_addr
        self.host = host
        self.port = port
        self._rtu: ModbusTcpServer | None = None
        self._ascii: asyncio.Server | None = None
        self._connections: set[_AsciiConnection] = set()

    async def listen(self) -> None:
        """Bind and serve in the background (on the running loop).

        Raises
        ------
        OSError
            If the address cannot be bound (a ``port`` taken).
        RuntimeError
            pymodbus' own error where it does not start listening (modbus-rtu).
        """
        if self.transport == "ascii":
            loop = asyncio.get_running_loop()
            self._ascii = await loop.create_server(
                lambda: _AsciiConnection(self.handle, self.ascii_addr, self._connections),
                self.host, self.port,
            )
            self.port = self._ascii.sockets[0].getsockname()[1]
            return
        adapter = ModbusAdapter(self.handle, self.unit, 0, corrupt_rtu, "modbus-rtu")
        self._rtu = adapter.server(
            ModbusTcpServer, framer=FramerType.RTU, address=(self.host, self.port)
        )
        await self._rtu.serve_forever(background=True)
        self.port = self._rtu.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]

    def close(self) -> None:
        """Stop listening and close every connection (idempotent)."""
        if self._rtu is not None:
            self._rtu.close()
            self._rtu = None
        if self._ascii is not None:
            self._ascii.close()  # stops accepting; the connections are closed here
            for conn in list(self._connections):
                conn.close()
            self._ascii = None
