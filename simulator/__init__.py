"""The emulated LDQ-412 DAQ module: device model, clocks, signal sources and wire servers.

from simulator import Emulator, ManualClock
with Emulator("modbus-tcp", clock=ManualClock()) as emu:
    ...  # open_daq(emu.url), emu.clock.advance(1.0), emu.faults.restart(), emu.truth
"""

from importlib import import_module
from typing import TYPE_CHECKING, Any

# Loaded on first use: the pytest plugin (simulator.pytest_plugin) is imported by every
# pytest run where loopcal is installed and must not pull in numpy and pymodbus for that.
_WHERE = {
    "Clock": "clock",
    "ManualClock": "clock",
    "RealClock": "clock",
    "SimClock": "clock",
    "LDQ412": "device",
    "DeviceError": "device",
    "TruthScan": "device",
    "Emulator": "emulator",
    "FaultInjector": "faults",
    "ConstantSource": "source",
    "SignalSource": "source",
    "TestSource": "source",
}

if TYPE_CHECKING:
    from .clock import Clock, ManualClock, RealClock, SimClock
    from .device import LDQ412, DeviceError, TruthScan
    from .emulator import Emulator
    from .faults import FaultInjector
    from .source import ConstantSource, SignalSource, TestSource


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(import_module(f".{_WHERE[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
