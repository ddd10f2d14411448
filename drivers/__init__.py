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

import lazy_loader as lazy

from . import errors
from .base import DAQ
from .errors import *  # noqa: F403 (the exceptions: errors.__all__)
from .records import Identity, Scan
from .registry import DriverLoadError, driver_for_url, open_daq, register_scheme
from .url import DaqUrl, parse_url

# the driver classes, loaded on first use (PEP 562, by lazy_loader)
__getattr__, _, _driver_classes = lazy.attach(
    __name__,
    submod_attrs={"modbus": ["ModbusDAQ"], "modbus_tcp": ["ModbusTcpDAQ"],
                  "modbus_rtu": ["ModbusRtuDAQ"], "ascii": ["AsciiDAQ"]},
)  # fmt: skip
del _

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
    *errors.__all__,
    *_driver_classes,
]
