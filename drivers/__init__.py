"""Drivers for the LDQ-412 four-channel LVDT acquisition module.

Open a module by URL; the scheme picks the driver::

    from loopcal.drivers import open_daq
    with open_daq("modbus-tcp://192.168.1.50:502?unit=1") as daq:
        for scan in daq.scans(timeout=1.0):  # every scan once, as the module makes them
            print(scan.counter64, scan.volts)

``daq.read_scans()`` returns at once what arrived since the previous call, for a read loop
of one's own.

The driver classes (and pymodbus, pyserial behind them) are imported on first use: a program
that needs only the datasheet's constants (``loopcal.drivers.ldq412``) or the URL parser does not
pay for them. Each is an entry point of the group ``loopcal.drivers``, where a package
installed beside loopcal declares another transport (:mod:`loopcal.drivers.registry`).
"""

import importlib

from . import errors
from .base import DAQ
from .errors import (
    DAQDisconnected,
    DAQError,
    DAQIdentityError,
    DAQInvalidCommand,
    DAQModbusException,
    DAQProtocolError,
    DAQTimeout,
)
from .records import Identity, Scan
from .registry import DriverLoadError, driver_for_url, open_daq, register_scheme
from .url import DaqUrl, parse_url

_LAZY = {"ModbusDAQ": "modbus", "ModbusTcpDAQ": "modbus_tcp", "ModbusRtuDAQ": "modbus_rtu",
         "AsciiDAQ": "ascii"}  # fmt: skip


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


__all__ = [
    "open_daq",
    "driver_for_url",
    "parse_url",
    "register_scheme",
    "DriverLoadError",
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
