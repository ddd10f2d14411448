"""LDQ-412 over Modbus RTU on RS-485 (pymodbus ModbusSerialClient, RTU framer).

URL: ``modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1&parity=N&stopbits=1&fifo=1``
(datasheet defaults: 115200 baud, 8N1, unit 1).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import ClassVar, Unpack

from pymodbus.client import ModbusSerialClient
from pymodbus.client.base import ModbusBaseSyncClient
from pymodbus.framer import FramerType

from . import ldq412
from .modbus import ModbusDAQ, ModbusOptions
from .url import DaqUrl, serial_options

#: silence on the line that ends a drain after an error, s (many RTU frame times)
QUIET_S = 0.005


class ModbusRtuDAQ(ModbusDAQ):
    """LDQ-412 on RS-485,
    ``modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1&parity=N&stopbits=1&fifo=1``.

    RTU has no transaction id, so after an error the port is reopened and the line
    drained until ``QUIET_S`` of silence (bounded by the timeout) before the next
    request; answers are checked for function code and length.

    Parameters
    ----------
    port : str
        Serial device, e.g. ``"/dev/ttyUSB0"``.
    baud : int
        Line speed, baud (> 0; default 115200).
    parity : {"N", "E", "O"}
        Parity (default none).
    stopbits : {1, 2}
        Stop bits (default 1).
    **options
        ``unit``, ``timeout``, ``use_fifo``, ``check_identity``: as
        :class:`~loopcal.drivers.modbus.ModbusDAQ`'s.

    Raises
    ------
    ValueError
        For a parity, stop bits or baud out of range; a unit as
        :class:`~loopcal.drivers.modbus.ModbusDAQ`.
    DAQError
        If the port cannot be opened, or as :class:`~loopcal.drivers.modbus.ModbusDAQ`.
    """

    scheme: ClassVar[str] = "modbus-rtu"
    url_params: ClassVar[frozenset[str]] = ModbusDAQ.url_params | {"baud", "parity", "stopbits"}

    def __init__(
        self,
        port: str,
        *,
        baud: int = ldq412.SERIAL_BAUD,
        parity: str = "N",
        stopbits: int = 1,
        **options: Unpack[ModbusOptions],
    ) -> None:
        if parity not in ("N", "E", "O"):
            raise ValueError(f"parity {parity!r} not N, E or O")
        if stopbits not in (1, 2):
            raise ValueError(f"stopbits {stopbits} not 1 or 2")
        if baud <= 0:
            raise ValueError(f"baud {baud} must be > 0")
        self.port, self.baud, self.parity, self.stopbits = port, baud, parity, stopbits
        super().__init__(f"modbus-rtu://{port}", {"baud": baud}, **options)

    @classmethod
    def url_options(cls, url: DaqUrl) -> dict[str, object]:
        return {
            **serial_options(url, "modbus-rtu:///dev/ttyUSB0"),
            **ModbusDAQ.common_options(url),
        }

    def _make_client(self, trace: Callable[[bool, bytes], bytes]) -> ModbusBaseSyncClient:
        return ModbusSerialClient(
            self.port,
            framer=FramerType.RTU,
            baudrate=self.baud,
            bytesize=8,
            parity=self.parity,
            stopbits=self.stopbits,
            timeout=self.timeout,
            retries=0,
            trace_packet=trace,
        )

    def _resync(self) -> None:
        client = self._client
        if not client.connect() or client.socket is None:
            return  # the next request reports DAQDisconnected
        ser = client.socket
        deadline = time.monotonic() + self.timeout
        try:
            last_rx = time.monotonic()
            while time.monotonic() < deadline:
                if ser.in_waiting:
                    ser.read(ser.in_waiting)
                    last_rx = time.monotonic()
                elif time.monotonic() - last_rx >= QUIET_S:
                    break
                time.sleep(0.001)
        except OSError:
            self._drop()
