"""The emulated LDQ-412 DAQ module: device model, clocks, signal sources and wire servers.

::

    from loopcal.simulator import Emulator, ManualClock
    with Emulator("modbus-tcp", clock=ManualClock()) as emu:
        ...  # open_daq(emu.url), emu.clock.advance(1.0), emu.faults.restart(), emu.truth
"""

from typing import TYPE_CHECKING

import lazy_loader as lazy

# Loaded on first use, as calibration/ and drivers/ do: the pytest plugin
# (loopcal.simulator.pytest_plugin) is imported by every pytest run where loopcal is installed and
# must not pull in numpy and pymodbus for that.
__getattr__, __dir__, __all__ = lazy.attach(
    __name__,
    submod_attrs={
        "clock": ["Clock", "ManualClock", "RealClock", "SimClock"],
        "device": ["LDQ412", "TruthScan"],
        "emulator": ["Emulator"],
        "faults": ["FaultInjector"],
        "registers": ["DeviceError"],
        "source": ["ConstantSource", "SignalSource", "TestSource"],
    },
)

if TYPE_CHECKING:  # the same names for type checkers, re-exported explicitly (``X as X``)
    from .clock import Clock as Clock
    from .clock import ManualClock as ManualClock
    from .clock import RealClock as RealClock
    from .clock import SimClock as SimClock
    from .device import LDQ412 as LDQ412
    from .device import TruthScan as TruthScan
    from .emulator import Emulator as Emulator
    from .faults import FaultInjector as FaultInjector
    from .registers import DeviceError as DeviceError
    from .source import ConstantSource as ConstantSource
    from .source import SignalSource as SignalSource
    from .source import TestSource as TestSource
