"""The names among which an emulated module's user chooses, in a module that imports
nothing: the transports the emulator serves and the scenarios the simulated mechanism
plays. A command's ``--help`` lists them without waiting for numpy or pymodbus; the
simulator's machinery takes them from here (:data:`loopcal.simulator.scenarios.SCENARIOS`).
"""

from __future__ import annotations

#: the wires the emulated LDQ-412 answers on: Modbus TCP, Modbus RTU and ASCII (the
#: serial ones over a pseudo-terminal)
TRANSPORTS = ("modbus-tcp", "modbus-rtu", "ascii")

#: how a serial transport's line reaches the driver: a pair of pseudo-terminals (a port
#: like /dev/ttyUSB0), or raw TCP through a serial device server on 127.0.0.1
#: (:mod:`loopcal.simulator.device_server`); the first is the default
LINES = ("pty", "tcp")

#: how the simulated plate moves: a technician's hand, pausing; still; a sweep; the
#: controller's task loop (:mod:`loopcal.simulator.scenarios`)
SCENARIO_NAMES = ("hand", "static", "sweep", "task")
