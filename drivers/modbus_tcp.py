"""LDQ-412 over Modbus TCP (pymodbus ModbusTcpClient).

URL: ``modbus-tcp://host[:port]?unit=1&fifo=1`` (port 502 and unit 1 by default).
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import ClassVar, Unpack

from pymodbus.client import ModbusTcpClient
from pymodbus.client.base import ModbusBaseSyncClient

from . import ldq412
from .modbus import ModbusDAQ, ModbusOptions
from .url import DaqUrl


class _TcpClient(ModbusTcpClient):
    """pymodbus' TCP client whose ``connect`` raises the socket's OSError (refused, timed
    out, no route, unknown host) where pymodbus' logs it and returns False: the driver's
    DAQDisconnected then carries it as its ``__cause__``, which tells a closed port from a
    host that does not answer (:mod:`loopcal.drivers.diagnosis`)."""

    def connect(self) -> bool:
        if self.socket:
            return True
        params = self.comm_params
        self.socket = socket.create_connection(
            (params.host, params.port), timeout=params.timeout_connect,
            source_address=params.source_address,
        )  # fmt: skip
        return True


class ModbusTcpDAQ(ModbusDAQ):
    """LDQ-412 on Ethernet, ``modbus-tcp://host[:port]?unit=1&fifo=1``.

    A timeout or protocol error closes the socket; the next call opens a fresh one (so a
    late answer can never be mistaken for the next one).

    Parameters
    ----------
    host : str
        Host name or address.
    port : int
        TCP port (default 502).
    **options
        ``unit``, ``timeout``, ``use_fifo``, ``check_identity``: as
        :class:`~loopcal.drivers.modbus.ModbusDAQ`'s.

    Raises
    ------
    ValueError, DAQError
        As :class:`~loopcal.drivers.modbus.ModbusDAQ`.
    """

    scheme: ClassVar[str] = "modbus-tcp"

    def __init__(
        self, host: str, port: int = ldq412.MODBUS_TCP_PORT, **options: Unpack[ModbusOptions]
    ) -> None:
        self.host, self.port = host, port
        super().__init__(f"modbus-tcp://{host}:{port}", {}, **options)

    @classmethod
    def url_options(cls, url: DaqUrl) -> dict[str, object]:
        if not url.host:
            raise ValueError(f"{url.raw}: no host (modbus-tcp://HOST[:PORT])")
        if url.port == 0:
            raise ValueError(f"{url.raw}: port 0 is not a port (default 502)")
        return {
            "host": url.host,
            "port": url.port or ldq412.MODBUS_TCP_PORT,
            **ModbusDAQ.common_options(url),
        }

    def _make_client(self, trace: Callable[[bool, bytes], bytes]) -> ModbusBaseSyncClient:
        return _TcpClient(
            self.host,
            port=self.port,
            timeout=self.timeout,
            retries=0,
            trace_packet=trace,
        )
