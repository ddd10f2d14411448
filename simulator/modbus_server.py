"""Modbus TCP and RTU servers for the emulated module, on pymodbus 3.16's server.

pymodbus does all framing, MBAP headers and CRCs. The module's behaviour is attached
through pymodbus' own extension points:

- a :class:`pymodbus.simulator.SimDevice` whose register blocks mirror the module's
  address map (a write outside the holding registers answers exception 02 inside
  pymodbus) and whose ``action`` hook applies writes (06, 16) to the device model and
  returns its exception codes (02/03);
- ``custom_pdu`` request classes: reads (03, 04) are answered by the device model itself,
  so that an answer may have fewer registers than asked (a truncated or short FIFO read,
  :mod:`loopcal.simulator.open_points`), and a FIFO-window read pops scans; reads of 0 or more
  than 125 registers answer 03 (the stock classes reject them while decoding, which
  pymodbus answers with 01), and every function the module does not implement (anything
  but 03, 04, 06, 16) answers 01 without reaching the datastore;
- answer latency (an open point): the answer is decided when the request arrives, then
  held back for the drawn delay on the server's event loop;
- ``trace_pdu`` drops requests the module would not see (another unit address, module
  off, stalled) before they touch the datastore, and ``trace_packet`` puts wire faults on
  outgoing frames (garbage before, broken CRC/MBAP) and silences anything still not due.

Decisions where the datasheet is silent: requests for another unit id get no answer on
TCP either (as on RS-485); a broadcast (unit 0) is ignored.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import struct
from collections.abc import Callable
from typing import TypeVar

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.framer import FramerType
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.decoders import DecodePDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadHoldingRegistersResponse,
    ReadInputRegistersRequest,
    ReadInputRegistersResponse,
)
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from loopcal.drivers.ldq412 import (
    HR_COUNT,
    IR_FIFO,
    IR_FIFO_END,
    IR_MODEL,
    IR_SNAPSHOT_LEN,
    SERIAL_BAUD,
)

from .device import LDQ412, DeviceOffError
from .handle import DeviceHandle
from .open_points import MODBUS_MAX_READ
from .registers import DeviceError
from .wire import Corrupter, corrupt_mbap, corrupt_rtu

SUPPORTED_FUNCTIONS = (3, 4, 6, 16)

_T = TypeVar("_T")
_S = TypeVar("_S", ModbusTcpServer, ModbusSerialServer)


class _CheckedReadHolding(ReadHoldingRegistersRequest):
    """Function 03, answered by the adapter; its count is checked when served (03), not
    while decoding (01)."""

    adapter: ModbusAdapter

    def decode(self, data: bytes) -> None:
        self.address, self.count = struct.unpack(">HH", data[:4])

    async def datastore_update(self, context: ModbusServerContext, device_id: int) -> ModbusPDU:
        if not 1 <= self.count <= MODBUS_MAX_READ:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        return await self.adapter.read(self.function_code, self.address, self.count)


class _CheckedReadInput(_CheckedReadHolding):
    """Function 04, likewise."""

    function_code = ReadInputRegistersRequest.function_code


class _Unsupported(ModbusPDU):
    """A function the module does not implement: answered with exception 01."""

    def decode(self, data: bytes) -> None:
        """Nothing to decode: the request is refused as a whole."""

    async def datastore_update(self, context: ModbusServerContext, device_id: int) -> ModbusPDU:
        return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_FUNCTION)


# RTU request sizes pymodbus cannot derive from its stock class (43 has sub-types).
_RTU_FRAME_SIZE_OVERRIDE = {43: 7}
_RTU_BARE_FRAME = 4


def custom_pdus(adapter: ModbusAdapter) -> list[type[ModbusPDU]]:
    """Request classes replacing pymodbus' stock ones in the module's servers.

    Reads (03, 04) are answered by ``adapter``. Every function code 1..127 other than 03,
    04, 06, 16 answers 01; the RTU frame size of a request comes from pymodbus' stock
    class where it has one (so an RTU request is consumed whole), else a bare
    ``address fc crc`` frame is assumed.

    Parameters
    ----------
    adapter : ModbusAdapter
        The server's adapter: it answers the reads.

    Returns
    -------
    list of type
        :class:`pymodbus.pdu.ModbusPDU` subclasses, for the servers' ``custom_pdu``: the
        two reads, then one class per unsupported function code.
    """
    classes: list[type[ModbusPDU]] = [
        type("_ReadHolding", (_CheckedReadHolding,), {"adapter": adapter}),
        type("_ReadInput", (_CheckedReadInput,), {"adapter": adapter}),
    ]
    for fc in range(1, 0x80):
        if fc in SUPPORTED_FUNCTIONS:
            continue
        stock = DecodePDU.pdu_table.get(fc, (None, None))[0]
        attrs = {
            "function_code": fc,
            "rtu_frame_size": _RTU_FRAME_SIZE_OVERRIDE.get(
                fc, stock.rtu_frame_size if stock else _RTU_BARE_FRAME
            ),
            "rtu_byte_count_pos": stock.rtu_byte_count_pos if stock else 0,
        }
        classes.append(type(f"_Unsupported{fc}", (_Unsupported,), attrs))
    return classes


class ModbusAdapter:
    """Connects pymodbus' hooks to the device model for one server.

    Parameters
    ----------
    handle : DeviceHandle
        The device, clock and wire faults, behind their lock.
    unit : int
        The module's unit id (requests for another get no answer).
    unit_index : int
        Where the unit id sits in an outgoing frame: 6 for TCP (after the MBAP's first
        six bytes), 0 for RTU.
    corrupter : callable
        ``corrupter(frame) -> bytes`` breaks a frame
        (:func:`~loopcal.simulator.wire.corrupt_mbap`,
        :func:`~loopcal.simulator.wire.corrupt_rtu`).
    transport : {"modbus-tcp", "modbus-rtu"}, default "modbus-tcp"
        Which one (the datasheet's latency bound differs).

    Attributes
    ----------
    handle : DeviceHandle
        As given.
    unit : int
        As given.
    unit_index : int
        As given.
    corrupter : callable
        As given.
    transport : str
        As given.
    """

    def __init__(
        self,
        handle: DeviceHandle,
        unit: int,
        unit_index: int,
        corrupter: Corrupter,
        transport: str = "modbus-tcp",
    ) -> None:
        self.handle = handle
        self.unit = unit
        self.unit_index = unit_index
        self.corrupter = corrupter
        self.transport = transport

    def sim_device(self) -> SimDevice:
        """The pymodbus device: the module's register map, with :meth:`action` as hook.

        A write outside the holding registers answers 02 inside pymodbus; the input
        register blocks are never reached (reads have request classes of their own).

        Returns
        -------
        pymodbus.simulator.SimDevice
        """
        regs = DataType.REGISTERS
        return SimDevice(
            id=self.unit,
            simdata=(
                [SimData(0, values=False, datatype=DataType.BITS)],  # never reached: fc 1/5/15
                [SimData(0, values=False, datatype=DataType.BITS)],  # never reached: fc 2
                [SimData(0, count=HR_COUNT, datatype=regs)],
                [  # never reached: fc 4 has its own request class
                    SimData(0, count=IR_SNAPSHOT_LEN, datatype=regs),
                    SimData(IR_FIFO, count=IR_FIFO_END - IR_FIFO, datatype=regs),
                    SimData(IR_MODEL, count=4, datatype=regs),
                ],
            ),
            action=self.action,
        )

    def server(self, server_class: type[_S], **where: object) -> _S:
        """A pymodbus server over the module: :meth:`sim_device`, this adapter's traces and
        the module's request classes (:func:`custom_pdus`).

        Parameters
        ----------
        server_class : type
            :class:`pymodbus.server.ModbusTcpServer` or
            :class:`pymodbus.server.ModbusSerialServer`.
        **where
            Where it serves: its own keyword arguments (an address; a port and framer).

        Returns
        -------
        ModbusTcpServer or ModbusSerialServer
            Not yet serving.
        """
        return server_class(
            self.sim_device(),
            trace_packet=self.trace_packet,
            trace_pdu=self.trace_pdu,  # type: ignore[arg-type]
            custom_pdu=custom_pdus(self),
            **where,
        )

    async def _latency(self) -> None:
        with self.handle.lock:
            delay = self.handle.wire.delay_s(self.transport)
        if delay > 0:
            await asyncio.sleep(delay)

    def _on_device(self, operation: Callable[[LDQ412], _T]) -> _T | ExcCodes:
        """Note the request and run ``operation`` on the device model synced to now: its
        result, or the exception code of the :class:`DeviceError` it raised."""
        self.handle.note_request()
        try:
            with self.handle.synced() as device:
                return operation(device)
        except DeviceError as exc:
            return ExcCodes(exc.code)
        except DeviceOffError:  # never sent: trace_packet silences an off module
            return ExcCodes.DEVICE_FAILURE

    async def read(self, function_code: int, address: int, count: int) -> ModbusPDU:
        """Answer a read (03 or 04) from the device model, after the drawn latency.

        Parameters
        ----------
        function_code : int
            3 (holding registers) or 4 (input registers).
        address : int
            First register.
        count : int
            Registers asked for.

        Returns
        -------
        pymodbus.pdu.ModbusPDU
            The registers (perhaps fewer than asked: a truncated or short FIFO read), or
            an exception response with the device's code.
        """
        rsp: ModbusPDU
        if function_code == 4:
            regs = self._on_device(lambda device: device.read_input_registers(address, count))
        else:
            regs = self._on_device(lambda device: device.read_holding_registers(address, count))
        if isinstance(regs, ExcCodes):
            rsp = ExceptionResponse(function_code, regs)
        else:
            cls = ReadInputRegistersResponse if function_code == 4 else ReadHoldingRegistersResponse
            rsp = cls(registers=regs)
        await self._latency()
        return rsp

    async def action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        """pymodbus access hook, reached by writes (06, 16) only.

        Reads and the functions the module does not implement have request classes of
        their own (:func:`custom_pdus`) that do not touch the datastore. Applies the write
        to the device model (after the drawn latency); pymodbus then stores the values,
        and its read-back of a function 06 (``set_values`` None, for the echo) returns
        exactly the value written.

        Parameters
        ----------
        function_code : int
            6 or 16.
        start_address : int
            pymodbus' start of the register block (not used).
        address : int
            First register written.
        count : int
            Registers written.
        registers : list of int
            pymodbus' copy of the block (not used).
        set_values : list of int, list of bool or None
            The values written; None for pymodbus' read-back of a 06.

        Returns
        -------
        pymodbus.constants.ExcCodes or None
            The device's exception code (02, 03), or None: applied.
        """
        if set_values is None:  # the read-back of a 06: the write was applied already
            return None
        values = [int(v) for v in set_values]
        code = self._on_device(lambda device: device.write_registers(address, values))
        await self._latency()
        return code

    def trace_pdu(self, sending: bool, pdu: ModbusPDU) -> ModbusPDU | None:
        """Drop (return None) a received request the module would not act on.

        Another unit id, a module not ready, stalled or with its link cut. Over TCP that
        includes a request on a connection opened before the module's latest power-on: the
        rebooted module knows nothing of it (the emulator's next housekeeping tick resets
        it), and answering it, say with the scans of a FIFO read, would lose them when the
        reset comes. A request received is noted first, dropped or not: a clock held until
        the first request must start even if the module does not answer yet (its first scan
        late).

        Parameters
        ----------
        sending : bool
            True for an outgoing response (passed through).
        pdu : pymodbus.pdu.ModbusPDU
            The request or response.

        Returns
        -------
        pymodbus.pdu.ModbusPDU or None
            ``pdu``, or None to drop it.
        """
        if sending:
            return pdu
        self.handle.note_request()
        with self.handle.synced() as device:
            if pdu.dev_id != self.unit or not self.handle.responsive_locked():
                return None
            if self.unit_index and device.boot != self.handle.links_boot:
                return None
        return pdu

    def trace_packet(self, sending: bool, packet: bytes) -> bytes:
        """Apply wire faults to an outgoing frame.

        Parameters
        ----------
        sending : bool
            True for an outgoing frame (incoming ones pass through).
        packet : bytes
            The frame.

        Returns
        -------
        bytes
            The frame with pending garbage and corruption applied
            (:meth:`WireFaults.outgoing <loopcal.simulator.wire.WireFaults.outgoing>`); b""
            (send nothing) for a frame of another unit or a module that would not answer
            now.
        """
        if not sending or not packet:
            return packet
        with self.handle.synced():
            if len(packet) <= self.unit_index or packet[self.unit_index] != self.unit:
                return b""
            if not self.handle.responsive_locked():
                return b""
            return self.handle.wire.outgoing(packet, self.corrupter)


def _reset(conn: object) -> None:
    """Abort a TCP connection with RST (SO_LINGER 0), as a rebooted host's stack does."""
    transport = getattr(conn, "transport", None)
    if transport is None:
        return
    sock = transport.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    transport.abort()


class ModbusTcpHost:
    """The module's Modbus TCP endpoint: a pymodbus server that can stop listening.

    A power-off stops listening (connection attempts are refused) and leaves established
    connections open but silent; power-on resets them (RST, as the module's rebooted
    stack does on the client's next segment) and listens again. A cut link resets the
    connections and refuses new ones until the link is back. The emulator's housekeeping
    decides when (the methods below only act).

    Parameters
    ----------
    handle, unit : DeviceHandle, int
        The device behind its lock, and the module's unit id, for the :attr:`adapter`
        (:class:`ModbusAdapter`).
    host : str, default "127.0.0.1"
        Listening address.
    port : int, default 0
        Listening port; 0: a free one, picked by the first :meth:`listen`.

    Attributes
    ----------
    adapter : ModbusAdapter
        The hooks into the device model.
    host : str
        As given.
    port : int
        The port listened on (after the first :meth:`listen`).
    listening : bool
        Whether new connections are accepted.
    """

    def __init__(self, handle: DeviceHandle, unit: int, host: str = "127.0.0.1", port: int = 0):
        self.adapter = ModbusAdapter(handle, unit, 6, corrupt_mbap, "modbus-tcp")
        self.host = host
        self.port = port
        self._servers: list[ModbusTcpServer] = []
        self.listening = False

    async def listen(self) -> None:
        """Start listening (on the first call, binds ``port``; 0 picks a free one).

        Each call starts a new pymodbus server on the same port; established connections
        of the earlier ones stay until :meth:`reset_connections`.

        Raises
        ------
        RuntimeError
            pymodbus' own error if the port cannot be bound (it says only that it could
            not start listening).
        """
        server = self.adapter.server(ModbusTcpServer, address=(self.host, self.port))
        await server.serve_forever(background=True)
        self._servers.append(server)
        self.port = server.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]
        self.listening = True

    def stop_listening(self) -> None:
        """Refuse new connections; established ones stay open."""
        if self.listening:
            self._servers[-1].transport.close()  # the asyncio.Server: stops accepting only
            self.listening = False

    def reset_connections(self) -> None:
        """RST every established connection and forget servers that have none left."""
        for server in self._servers:
            for conn in list(server.active_connections.values()):
                _reset(conn)
        keep = self._servers[-1:] if self.listening else []
        for server in self._servers:
            if server not in keep:
                server.close()
        self._servers = keep

    def close(self) -> None:
        """Stop listening and close every server and its connections (an orderly close)."""
        self.stop_listening()
        for server in self._servers:
            server.close()
        self._servers = []


class ModbusRtuHost:
    """The module's Modbus RTU endpoint: a pymodbus serial server on a pty slave.

    Parameters
    ----------
    handle, unit : DeviceHandle, int
        The device behind its lock, and the module's unit id, for the :attr:`adapter`
        (:class:`ModbusAdapter`).
    port_path : str
        The serial device the server opens (the pty link's
        :attr:`~loopcal.simulator.pty.PtyLink.device_path`).
    baud : int, default 115200
        Baud rate the server opens the serial device with.

    Attributes
    ----------
    adapter : ModbusAdapter
        The hooks into the device model.
    port_path : str
        As given.
    baud : int
        As given.
    """

    def __init__(self, handle: DeviceHandle, unit: int, port_path: str, baud: int = SERIAL_BAUD):
        self.adapter = ModbusAdapter(handle, unit, 0, corrupt_rtu, "modbus-rtu")
        self.port_path = port_path
        self.baud = baud
        self._server: ModbusSerialServer | None = None

    async def listen(self) -> None:
        """Open the serial device and serve RTU frames on it in the background."""
        self._server = self.adapter.server(
            ModbusSerialServer, framer=FramerType.RTU, port=self.port_path, baudrate=self.baud
        )
        await self._server.serve_forever(background=True)

    def close(self) -> None:
        """Stop serving and close the serial device (idempotent)."""
        if self._server is not None:
            self._server.close()
            self._server = None
