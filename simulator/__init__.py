"""The emulated LDQ-412 DAQ module: device model, clocks, signal sources and wire servers.

from simulator import Emulator, ManualClock
with Emulator("modbus-tcp", clock=ManualClock()) as emu:
    ...  # open_daq(emu.url), emu.clock.advance(1.0), emu.faults.restart(), emu.truth
"""

from .clock import Clock, ManualClock, RealClock, SimClock
from .device import LDQ412, DeviceError, TruthScan
from .emulator import Emulator
from .faults import FaultInjector
from .source import ConstantSource, SignalSource, TestSource

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
