"""The emulated LDQ-412 DAQ module: device model, clocks, signal sources and wire servers.

::

    from loopcal.simulator import Emulator, ManualClock
    with Emulator("modbus-tcp", clock=ManualClock()) as emu:
        ...  # open_daq(emu.url), emu.clock.advance(1.0), emu.faults.restart(), emu.truth
"""

import importlib
from typing import TYPE_CHECKING

# Loaded on first use, as calibration/ and drivers/ do: the pytest plugin
# (loopcal.simulator.pytest_plugin) is imported by every pytest run where loopcal is installed and
# must not pull in numpy and pymodbus for that.
_LAZY = {
    "Clock": "clock", "ManualClock": "clock", "RealClock": "clock", "SimClock": "clock",
    "LDQ412": "device", "DeviceError": "registers", "TruthScan": "device",
    "Emulator": "emulator",
    "FaultInjector": "faults",
    "ConstantSource": "source", "SignalSource": "source", "TestSource": "source",
}  # fmt: skip

if TYPE_CHECKING:
    from .clock import Clock, ManualClock, RealClock, SimClock
    from .device import LDQ412, TruthScan
    from .emulator import Emulator
    from .faults import FaultInjector
    from .registers import DeviceError
    from .source import ConstantSource, SignalSource, TestSource


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = [
    "LDQ412",
    "Clock",
    "ConstantSource",
    "DeviceError",
    "Emulator",
    "FaultInjector",
    "ManualClock",
    "RealClock",
    "SignalSource",
    "SimClock",
    "TestSource",
    "TruthScan",
]
