"""Typed errors raised by the LDQ-412 drivers.

Every failure of a driver call surfaces as one of these (never as a pymodbus, pyserial or
socket exception). A driver stays usable after any of them: the next call reconnects or
resynchronises as needed, so once the fault has cleared the next call succeeds again.
"""

from __future__ import annotations


class DAQError(Exception):
    """Base class of every driver error."""


class DAQTimeout(DAQError, TimeoutError):
    """No byte of an answer arrived within the timeout (datasheet: 100 ms)."""


class DAQProtocolError(DAQError):
    """Bytes arrived but did not form a valid answer.

    Garbage, a partial frame, a wrong CRC / checksum / MBAP header, a wrong length, a
    non-hex digit, an answer to another request, or values outside their datasheet range.
    """


class DAQInvalidCommand(DAQProtocolError):
    """The module rejected an ASCII command with ``?AA`` (invalid command)."""


class DAQModbusException(DAQError):
    """The module answered a Modbus request with an exception response.

    Attributes:
        code: Modbus exception code (2 = illegal data address, 3 = illegal data value).
        function_code: function code of the request (without the 0x80 bit).
    """

    ILLEGAL_FUNCTION = 1
    ILLEGAL_DATA_ADDRESS = 2
    ILLEGAL_DATA_VALUE = 3

    def __init__(self, code: int, function_code: int, message: str = "") -> None:
        self.code = code
        self.function_code = function_code
        super().__init__(
            message or f"Modbus exception {code:#04x} on function {function_code:#04x}"
        )


class DAQIdentityError(DAQError):
    """The device at the URL is not an LDQ-412 (model code / model name mismatch)."""


class DAQDisconnected(DAQError, ConnectionError):
    """The transport is not connected (connection refused or reset, port gone)."""


__all__ = [
    "DAQError",
    "DAQTimeout",
    "DAQProtocolError",
    "DAQInvalidCommand",
    "DAQModbusException",
    "DAQIdentityError",
    "DAQDisconnected",
]
