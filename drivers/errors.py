"""Typed errors raised by the LDQ-412 drivers.

Every failure of a driver call surfaces as one of these (never as a pymodbus, pyserial or
socket exception). A driver stays usable after any of them: the next call reconnects or
resynchronises as needed, so once the fault has cleared the next call succeeds again.
"""

from __future__ import annotations


class DAQError(Exception):
    """Base class of every driver error; ``except DAQError`` catches them all.

    Parameters
    ----------
    message : str
        What failed, starting with the driver's URL.
    """


class DAQTimeout(DAQError, TimeoutError):
    """No byte of an answer arrived within the driver's timeout (datasheet: 100 ms), or a
    stream (:meth:`DAQ.scans`) got no new scan within its own ``timeout``.

    Also a :class:`TimeoutError`. A stream's is chained (``__cause__``) from the driver's
    last error, if one kept the scans away.

    Parameters
    ----------
    message : str
        What timed out, starting with the driver's URL.
    """


class DAQProtocolError(DAQError):
    """Bytes arrived but did not form a valid answer.

    Garbage, a partial frame, a wrong CRC / checksum / MBAP header, a wrong length, a
    non-hex digit, an answer to another request, or values outside their datasheet range.

    Parameters
    ----------
    message : str
        What was wrong with the answer (with the bytes, where short enough).
    """


class DAQInvalidCommand(DAQProtocolError):
    """The module rejected an ASCII command with ``?AA`` (invalid command).

    Parameters
    ----------
    message : str
        The module's address and the rejection.
    """


class DAQModbusException(DAQError):
    """The module answered a Modbus request with an exception response.

    Parameters
    ----------
    code : int
        The Modbus exception code (1 illegal function, 2 illegal data address, 3 illegal
        data value).
    function_code : int
        The request's function code (without the 0x80 bit), e.g. 4 for read input
        registers.
    message : str
        What was asked; by default the codes.

    Attributes
    ----------
    code, function_code : int
        As given.
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
    """The device at the URL is not an LDQ-412 (its model code or model name is another),
    raised at connect unless ``check_identity=False``.

    Parameters
    ----------
    message : str
        The URL and what the device said it is.
    """


class DAQDisconnected(DAQError, ConnectionError):
    """The transport is not connected: connection refused or reset, a port gone, or the
    driver closed. Also a :class:`ConnectionError`.

    Parameters
    ----------
    message : str
        The URL and the transport's error.
    """


__all__ = [
    "DAQError",
    "DAQTimeout",
    "DAQProtocolError",
    "DAQInvalidCommand",
    "DAQModbusException",
    "DAQIdentityError",
    "DAQDisconnected",
]
