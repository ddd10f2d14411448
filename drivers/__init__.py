"""Drivers for the LDQ-412 four-channel LVDT acquisition module.

Open a module by URL; the scheme picks the driver::

    from drivers import open_daq
    with open_daq("modbus-tcp://192.168.1.50:502?unit=1") as daq:
        scans = daq.read_scans()
"""

from . import errors
from .ascii import AsciiDAQ
from .base import (
    DAQ,
    DaqUrl,
    Identity,
    Scan,
    driver_for_url,
    open_daq,
    parse_url,
    register_scheme,
)
from .errors import (
    DAQDisconnected,
    DAQError,
    DAQIdentityError,
    DAQInvalidCommand,
    DAQModbusException,
    DAQProtocolError,
    DAQTimeout,
)
from .modbus import ModbusDAQ
from .modbus_rtu import ModbusRtuDAQ
from .modbus_tcp import ModbusTcpDAQ

__all__ = [
    "open_daq",
    "driver_for_url",
    "parse_url",
    "register_scheme",
    "DAQ",
    "DaqUrl",
    "Identity",
    "Scan",
    "errors",
    "DAQError",
    "DAQTimeout",
    "DAQProtocolError",
    "DAQInvalidCommand",
    "DAQModbusException",
    "DAQIdentityError",
    "DAQDisconnected",
    "ModbusDAQ",
    "ModbusTcpDAQ",
    "ModbusRtuDAQ",
    "AsciiDAQ",
]
