"""Constants and pure conversions of the LDQ-412 DAQ module (docs/daq.md).

This module is the single place where the datasheet's numbers live. The drivers use
it to talk to the module; the simulator uses it to imitate the module. It does no I/O.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # numpy is imported by the conversions that use it: the constants are
    import numpy as np  # read by every command's --help, which must not wait for numpy

MODEL_CODE = 0x0412
MODEL_NAME = "LDQ412"
N_CHANNELS = 4
ADC_BITS = 12
CODE_MAX = (1 << ADC_BITS) - 1  # 4095
V_MIN, V_MAX = -10.0, 10.0
V_SPAN = V_MAX - V_MIN
CHANNEL_SKEW_S = 250e-6  # channel i is converted i * 250 us after channel 1
SCAN_RATE_DEFAULT_HZ = 20
SCAN_RATE_MIN_HZ, SCAN_RATE_MAX_HZ = 1, 200
OVERSAMPLING_CHOICES = (1, 2, 4, 8, 16)
FIFO_DEPTH = 256
FIFO_MAX_SCANS_PER_READ = 20
FIFO_SCAN_REGS = 6  # counter hi, counter lo, ch1..ch4
FIFO_FILLER = 0xFFFF
U32_MOD = 1 << 32

# Modbus defaults
MODBUS_TCP_PORT = 502
MODBUS_UNIT = 1
SERIAL_BAUD = 115200

# Input registers (function 04), zero-based
IR_COUNTER = 0  # 0-1, uint32 high word first
IR_TIME = 2  # 2-3, uint32 microseconds
IR_CODES = 4  # 4-7
IR_STATUS = 8
IR_FIFO_LEVEL = 9
IR_SNAPSHOT_LEN = 10  # one consistent read of 0..9
IR_FIFO = 256
IR_FIFO_END = IR_FIFO + FIFO_MAX_SCANS_PER_READ * FIFO_SCAN_REGS  # exclusive
IR_MODEL = 512
IR_FIRMWARE = 513
IR_SERIAL = 514  # 514-515
IR_IDENTITY_LEN = 4

# Holding registers (functions 03, 06, 16)
HR_SCAN_RATE = 0
HR_OVERSAMPLING = 1
HR_CLEAR_FIFO = 2
HR_CLEAR_RESTART = 3
HR_ASCII_CHECKSUM = 4
HR_COUNT = 5

# Status register bits
STATUS_RAIL_MASK = 0x000F  # bit i-1: channel i at the rail
STATUS_FAULT_MASK = 0x00F0  # bit 4+i-1: channel i sensor fault
STATUS_OVERFLOW = 1 << 8
STATUS_RESTART = 1 << 9

# Timing (datasheet section "Timing")
HOST_TIMEOUT_S = 0.100
POWER_CYCLE_S = 2.0

# ASCII protocol
ASCII_CR = b"\r"
ASCII_DEFAULT_ADDR = 0x01


def volts_to_code(volts: np.ndarray | float) -> np.ndarray:
    """The ADC's exact transfer function: ``clamp(floor((V + 10) * 4096 / 20), 0, 4095)``.

    Parameters
    ----------
    volts : array_like or float
        Input voltages, V, any shape.

    Returns
    -------
    numpy.ndarray
        int64 codes 0..4095, the same shape.
    """
    import numpy as np

    v = np.asarray(volts, dtype=float)
    code = np.floor((v - V_MIN) * (CODE_MAX + 1) / V_SPAN)
    return np.clip(code, 0, CODE_MAX).astype(np.int64)


def code_to_volts(code: np.ndarray | int) -> np.ndarray:
    """Mid-code reconstruction: ``V = (code + 0.5) * 20 / 4096 - 10``.

    Parameters
    ----------
    code : array_like or int
        ADC codes, 0..4095, any shape.

    Returns
    -------
    numpy.ndarray
        Voltages, V, float64, the same shape.
    """
    import numpy as np

    c = np.asarray(code, dtype=float)
    return (c + 0.5) * V_SPAN / (CODE_MAX + 1) + V_MIN


def at_rail(code: np.ndarray | int) -> np.ndarray:
    """Where a code is at the rail (0 or 4095): the reading is not trustworthy.

    Parameters
    ----------
    code : array_like or int
        ADC codes, any shape.

    Returns
    -------
    numpy.ndarray
        bool, the same shape.
    """
    import numpy as np

    c = np.asarray(code)
    return (c == 0) | (c == CODE_MAX)


def ascii_checksum(frame: bytes) -> bytes:
    """The ASCII protocol's checksum of a frame.

    Parameters
    ----------
    frame : bytes
        The frame up to the checksum (without CR).

    Returns
    -------
    bytes
        Two uppercase hex digits: the sum of the bytes modulo 256.
    """
    return b"%02X" % (sum(frame) & 0xFF)


def split_u32(value: int) -> tuple[int, int]:
    """A uint32 as two 16-bit registers, high word first.

    Parameters
    ----------
    value : int
        Taken modulo 2**32.

    Returns
    -------
    tuple[int, int]
        ``(high, low)``, 0..65535 each.
    """
    value &= 0xFFFFFFFF
    return value >> 16, value & 0xFFFF


def join_u32(hi: int, lo: int) -> int:
    """Two 16-bit registers, high word first, as a uint32.

    Parameters
    ----------
    hi, lo : int
        The registers (only their low 16 bits count).

    Returns
    -------
    int
        0..2**32-1.
    """
    return ((hi & 0xFFFF) << 16) | (lo & 0xFFFF)
