"""LDQ-412 over its vendor ASCII protocol (pyserial).

URL: ``ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=1`` (address as two hex digits,
default 01; checksum 0/1 must match the module's checksum mode, default 0), or
``ascii://HOST:PORT?addr=01`` for a line behind a serial device server in raw TCP mode
(:mod:`loopcal.drivers.url`).

The protocol has no FIFO: read_scans polls ``#AA`` once per call and returns the scan if
its counter is new; scans the module made between two polls are reported in Scan.missed.
The protocol has no serial-number query (Identity.serial is None) and no command to clear
the restart flag (clear_restart returns False); the restart flag therefore stays set after
the first power-on, and later restarts are detected by the counter going backwards, or,
where polls failed long enough for the counter to come back past where it was, by the
host's clock (:mod:`loopcal.drivers.sequence`): a restart in such a stretch is not
detectable over ASCII only if the module was on before it and off for less than
``ANSWER_AGE_S`` (3 s) together.

Frames are built and parsed here (the vendor protocol is not a library's). The parser is
strict: exact lengths, hex digits only, the ``>`` / ``!AA`` / ``?AA`` leads, uppercase
checksum digits that match; anything else is a DAQProtocolError. Before every command the
input buffer is discarded, so leftovers of a fault never poison the next answer.
"""

from __future__ import annotations

import re
import time
from typing import ClassVar

import serial

try:  # pyserial's POSIX port lets termios.error (not an OSError) through: a port gone away
    import termios

    _PORT_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
except ImportError:  # pragma: no cover - not POSIX
    _PORT_ERRORS = (serial.SerialException, OSError)

from . import ldq412
from .base import DAQ, Identity, Scan
from .errors import (
    DAQDisconnected,
    DAQIdentityError,
    DAQInvalidCommand,
    DAQProtocolError,
    DAQTimeout,
)
from .lines import bytes_waiting
from .sequence import RawSnapshot
from .url import DaqUrl, line_url, serial_options

CR = ldq412.ASCII_CR
_HEX_UPPER = frozenset(b"0123456789ABCDEF")
_HEX_ANY = _HEX_UPPER | frozenset(b"abcdef")
_PRINTABLE = frozenset(range(0x20, 0x7F))
_FIRMWARE_RE = re.compile(r"^(\d{1,3})\.(\d{2})$")
#: '>' + counter (8) + time (8) + 4 codes (3 each) + status (4)
SCAN_BODY_LEN = 1 + 8 + 8 + 3 * ldq412.N_CHANNELS + 4
#: longest answer we wait for (the scan answer plus checksum digits and CR)
MAX_ANSWER_LEN = SCAN_BODY_LEN + 3


def encode_command(lead: str, addr: int, tail: str = "", *, checksum: bool) -> bytes:
    """Build a command frame: lead + AA (two uppercase hex digits) + tail [+ checksum] + CR.

    Parameters
    ----------
    lead : {"#", "$", "%"}
        Data, query or set command.
    addr : int
        Module address, 0..255.
    tail : str
        What follows the address, e.g. ``"M"``, ``"R0014"`` (ASCII).
    checksum : bool
        Append the two checksum digits (the module's checksum mode).

    Returns
    -------
    bytes
        The frame, e.g. ``b"#01\\r"``.

    Raises
    ------
    ValueError
        For another lead.
    """
    if lead not in ("#", "$", "%"):
        raise ValueError(f"command lead {lead!r}")
    frame = f"{lead}{addr:02X}{tail}".encode("ascii")
    if checksum:
        frame += ldq412.ascii_checksum(frame)
    return frame + CR


def _hex(field: bytes, what: str, *, upper_only: bool = False) -> int:
    allowed = _HEX_UPPER if upper_only else _HEX_ANY
    if not field or any(b not in allowed for b in field):
        raise DAQProtocolError(f"{what}: {field!r} is not hex")
    return int(field, 16)


def unframe(line: bytes, *, checksum: bool) -> bytes:
    """The body of an answer line, its framing checked.

    Parameters
    ----------
    line : bytes
        The answer, ending in CR.
    checksum : bool
        The line carries two uppercase checksum digits before the CR.

    Returns
    -------
    bytes
        The body, without CR and checksum.

    Raises
    ------
    DAQProtocolError
        For a line without CR, an empty one, non-printable bytes, or a missing, malformed
        or wrong checksum.
    """
    if not line.endswith(CR):
        raise DAQProtocolError(f"partial answer (no CR): {line!r}")
    body = line[:-1]
    if not body:
        raise DAQProtocolError("empty answer")
    if any(b not in _PRINTABLE for b in body):
        raise DAQProtocolError(f"non-printable bytes in answer: {line!r}")
    if checksum:
        if len(body) < 3:
            raise DAQProtocolError(f"answer too short for a checksum: {line!r}")
        body, digits = body[:-2], body[-2:]
        _hex(digits, "checksum", upper_only=True)
        if digits != ldq412.ascii_checksum(body):
            raise DAQProtocolError(
                f"bad checksum in {line!r}: expected {ldq412.ascii_checksum(body)!r}"
            )
    return body


def _check_not_rejected(body: bytes, addr: int) -> None:
    if body[:1] == b"?":
        if body == b"?%02X" % addr:
            raise DAQInvalidCommand(f"module {addr:02X} answered ?{addr:02X} (invalid command)")
        raise DAQProtocolError(f"malformed or foreign rejection: {body!r}")


def _data_answer(body: bytes, addr: int, digits: int, what: str) -> bytes:
    """The digits of a data answer, ``>`` + ``digits`` characters (not yet checked to be
    hex), unless it is a ``?AA`` rejection (DAQInvalidCommand) or has another lead or
    length (DAQProtocolError naming ``what`` answer was expected)."""
    _check_not_rejected(body, addr)
    if body[:1] != b">" or len(body) != 1 + digits:
        raise DAQProtocolError(f"not a {what} answer ('>' + {digits} hex digits): {body!r}")
    return body[1:]


def parse_scan(body: bytes, addr: int) -> RawSnapshot:
    """Decode a ``#AA`` answer: the latest scan.

    Parameters
    ----------
    body : bytes
        The answer's body (:func:`unframe`): ``>`` + counter (8 hex) + time (8 hex) +
        ch1..ch4 (3 hex each) + status (4 hex).
    addr : int
        The module's address (a ``?AA`` rejection names it).

    Returns
    -------
    RawSnapshot
        ``fifo_level`` None.

    Raises
    ------
    DAQInvalidCommand
        For ``?AA``.
    DAQProtocolError
        For anything else that is not such an answer.
    """
    digits = _data_answer(body, addr, SCAN_BODY_LEN - 1, "scan")
    counter = _hex(digits[0:8], "counter")
    time_us = _hex(digits[8:16], "time")
    c = [_hex(digits[16 + 3 * i : 19 + 3 * i], f"channel {i + 1}") for i in range(4)]
    status = _hex(digits[28:32], "status")
    return RawSnapshot(counter, time_us, (c[0], c[1], c[2], c[3]), status)


def parse_channel(body: bytes, addr: int) -> int:
    """Decode a ``#AAn`` answer: one channel's code.

    Parameters
    ----------
    body : bytes
        The answer's body, ``>`` + 3 hex digits.
    addr : int
        The module's address.

    Returns
    -------
    int
        The code, 0..4095.

    Raises
    ------
    DAQInvalidCommand, DAQProtocolError
        As :func:`parse_scan`.
    """
    return _hex(_data_answer(body, addr, 3, "channel"), "code")


def parse_ack(body: bytes, addr: int) -> bytes:
    """Decode a ``!AA...`` answer (to ``$`` and ``%`` commands).

    Parameters
    ----------
    body : bytes
        The answer's body.
    addr : int
        The module's address, which the answer must name.

    Returns
    -------
    bytes
        The payload after ``!AA`` (possibly empty).

    Raises
    ------
    DAQInvalidCommand
        For ``?AA``.
    DAQProtocolError
        If the answer does not start with ``!AA``.
    """
    _check_not_rejected(body, addr)
    head = b"!%02X" % addr
    if body[:3] != head:
        raise DAQProtocolError(f"expected an answer starting {head!r}: {body!r}")
    return body[3:]


def parse_firmware(payload: bytes) -> str:
    """Decode the ``$AAF`` payload: the firmware version.

    Parameters
    ----------
    payload : bytes
        ``M.mm`` (1-3 digits, a dot, 2 digits).

    Returns
    -------
    str
        ``"M.mm"``, leading zeros of the major dropped.

    Raises
    ------
    DAQProtocolError
        If the payload is not ``M.mm``.
    """
    m = _FIRMWARE_RE.match(payload.decode("ascii", errors="replace"))
    if not m:
        raise DAQProtocolError(f"firmware version {payload!r} is not M.mm")
    return f"{int(m.group(1))}.{m.group(2)}"


def parse_rate(payload: bytes) -> int:
    """Decode the ``$AAR`` payload: the scan rate.

    Parameters
    ----------
    payload : bytes
        4 hex digits.

    Returns
    -------
    int
        Scan rate, Hz (1..200).

    Raises
    ------
    DAQProtocolError
        If it is not 4 hex digits, or outside the datasheet's 1..200 Hz.
    """
    if len(payload) != 4:
        raise DAQProtocolError(f"scan rate {payload!r} is not 4 hex digits")
    rate = _hex(payload, "scan rate")
    if not ldq412.SCAN_RATE_MIN_HZ <= rate <= ldq412.SCAN_RATE_MAX_HZ:
        raise DAQProtocolError(f"scan rate {rate} Hz outside the datasheet range")
    return rate


class AsciiDAQ(DAQ):
    """LDQ-412 on RS-232/RS-485 speaking the vendor ASCII protocol,
    ``ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=0&parity=N&stopbits=1``.

    No FIFO: :meth:`read_scans` polls once per call (module docstring).

    Parameters
    ----------
    port : str
        Serial device, e.g. ``"/dev/ttyUSB0"``, or a pyserial URL: a serial device
        server's TCP port is ``"socket://HOST:PORT"`` (its baud rate, parity and stop bits
        are the device server's settings; pyserial ignores these arguments on it).
    baud : int
        Line speed, baud (default 115200).
    addr : int
        Module address, 0..255 (default 1; two hex digits in the URL).
    checksum : bool
        The module's checksum mode (default off).
    parity : {"N", "E", "O"}
        Parity (default none).
    stopbits : {1, 2}
        Stop bits (default 1).
    timeout : float
        s without an answer before a call raises DAQTimeout (default 0.1).
    check_identity : bool
        Raise DAQIdentityError unless the module answers ``$AAM`` with ``LDQ412``.

    Raises
    ------
    ValueError
        For an address, parity or stop bits out of range.
    DAQError
        If the port cannot be opened, the module does not answer at connect (the message
        asks whether addr and checksum are the module's), or it is not an LDQ-412.
    """

    scheme: ClassVar[str] = "ascii"
    url_params: ClassVar[frozenset[str]] = frozenset(
        {"baud", "addr", "checksum", "parity", "stopbits"}
    )

    def __init__(
        self,
        port: str,
        *,
        baud: int = ldq412.SERIAL_BAUD,
        addr: int = ldq412.ASCII_DEFAULT_ADDR,
        checksum: bool = False,
        parity: str = "N",
        stopbits: int = 1,
        timeout: float = ldq412.HOST_TIMEOUT_S,
        check_identity: bool = True,
    ) -> None:
        if not 0 <= addr <= 0xFF:
            raise ValueError(f"ASCII address {addr} outside 00..FF")
        if parity not in ("N", "E", "O"):
            raise ValueError(f"parity {parity!r} not N, E or O")
        if stopbits not in (1, 2):
            raise ValueError(f"stopbits {stopbits} not 1 or 2")
        self.port, self.baud, self.addr, self.checksum = port, baud, addr, checksum
        self.parity, self.stopbits, self.timeout = parity, stopbits, timeout
        self.url = f"{line_url('ascii', port)}?baud={baud}&addr={addr:02X}&checksum={int(checksum)}"
        self._ser: serial.SerialBase | None = None
        self._closed = False
        self._pending: list[Scan] = []
        self._connect_and_identify(self._open, check_identity)

    @classmethod
    def url_options(cls, url: DaqUrl) -> dict[str, object]:
        line = serial_options(url, "ascii:///dev/ttyUSB0")
        addr_text = url.params.get("addr", f"{ldq412.ASCII_DEFAULT_ADDR:02X}")
        if not 1 <= len(addr_text) <= 2:
            raise ValueError(f"{url.raw}: addr={addr_text!r} is not two hex digits")
        return {
            **line,
            "addr": url.get_int("addr", ldq412.ASCII_DEFAULT_ADDR, base=16, lo=0, hi=0xFF),
            "checksum": url.get_bool("checksum", False),
        }

    # -- transport -----------------------------------------------------------------------

    def _open(self) -> serial.SerialBase:
        if self._closed:
            raise DAQDisconnected(f"{self.url}: driver closed")
        if self._ser is None:
            try:
                self._ser = serial.serial_for_url(
                    self.port,
                    baudrate=self.baud,
                    bytesize=8,
                    parity=self.parity,
                    stopbits=self.stopbits,
                    timeout=min(self.timeout, 0.01),
                    write_timeout=self.timeout,
                    # one program owns a serial line (pymodbus opens RTU ports so too)
                    exclusive=True,
                )
            except (serial.SerialException, OSError, ValueError) as exc:
                raise DAQDisconnected(f"{self.url}: cannot open port: {exc}") from exc
        return self._ser

    def _drop(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:  # noqa: BLE001 - closing a broken port must not raise
                pass
            self._ser = None

    def transact(self, command: bytes) -> bytes:
        """Send one complete command frame and read its answer; for diagnostics too.

        Parameters
        ----------
        command : bytes
            A frame (:func:`encode_command`), ending in CR.

        Returns
        -------
        bytes
            The answer's body (CR and checksum stripped, checked).

        Raises
        ------
        DAQTimeout
            If no byte arrives within the timeout.
        DAQProtocolError
            For a partial or malformed answer.
        DAQDisconnected
            If the port fails (or the driver is closed).
        """
        ser = self._open()
        try:
            ser.reset_input_buffer()
            ser.write(command)
            line = self._read_line(ser)
        except serial.SerialTimeoutException as exc:
            self._drop()
            raise DAQTimeout(f"{self.url}: write timed out") from exc
        except _PORT_ERRORS as exc:
            self._drop()
            raise DAQDisconnected(f"{self.url}: {exc}") from exc
        if not line:
            raise DAQTimeout(f"{self.url}: no answer to {command!r} within {self.timeout} s")
        try:
            return unframe(line, checksum=self.checksum)
        except DAQProtocolError as exc:
            raise DAQProtocolError(f"{self.url}: answer to {command!r}: {exc}") from None

    def _read_line(self, ser: serial.SerialBase) -> bytes:
        """Bytes up to and including the first CR, or what arrived before the deadline."""
        deadline = time.monotonic() + self.timeout
        buf = bytearray()
        while True:
            waiting = bytes_waiting(ser)
            chunk = ser.read(waiting if waiting else 1)
            if chunk:
                buf += chunk
                cr = buf.find(CR)
                if cr >= 0:
                    # Bytes after the CR cannot belong to this answer; the next command
                    # discards them with the input buffer.
                    return bytes(buf[: cr + 1])
                if len(buf) > 4 * MAX_ANSWER_LEN:
                    return bytes(buf)  # a babbling line: unframe() reports it
            if time.monotonic() >= deadline:
                return bytes(buf)

    def _command(self, lead: str, tail: str = "") -> bytes:
        return self.transact(encode_command(lead, self.addr, tail, checksum=self.checksum))

    # -- device functions ----------------------------------------------------------------

    def _read_identity(self, check: bool) -> Identity:
        model = self._read_model()
        if check and model != ldq412.MODEL_NAME:
            # "$AAM", "$AAF" and "$AAR" are all answered "!AA...": a late answer to an
            # earlier request (a connect given up on: ci53, "model '3.07'", its firmware)
            # reads as this one's. Asked again on a quiet line, a module that is not an
            # LDQ-412 says so again
            self._quiet_line()
            model = self._read_model()
        if check and model != ldq412.MODEL_NAME:
            raise DAQIdentityError(f"{self.url}: model {model!r}, expected {ldq412.MODEL_NAME!r}")
        firmware = parse_firmware(parse_ack(self._command("$", "F"), self.addr))
        return Identity(model, firmware, None, None)

    def _read_model(self) -> str:
        try:
            return parse_ack(self._command("$", "M"), self.addr).decode("ascii")
        except (DAQTimeout, DAQProtocolError) as exc:
            raise type(exc)(
                f"{exc} (is checksum={int(self.checksum)} the module's checksum mode, and "
                f"addr={self.addr:02X} its address?)"
            ) from exc

    def _quiet_line(self) -> None:
        """Drop what the line brings until it has been quiet for the timeout (for at most
        three timeouts): late answers to earlier requests, no one's now.

        Raises
        ------
        DAQDisconnected
            If the port fails.
        """
        ser = self._open()
        start = last = time.monotonic()
        end = start + 3 * self.timeout
        try:
            while (now := time.monotonic()) - last < self.timeout and now < end:
                if ser.read(bytes_waiting(ser) or 1):  # the port's read waits 10 ms at most
                    last = time.monotonic()
        except _PORT_ERRORS as exc:
            self._drop()
            raise DAQDisconnected(f"{self.url}: {exc}") from exc

    def _poll(self) -> Scan:
        sent = time.monotonic()
        body = self._command("#")
        host_time = time.monotonic()
        snap = parse_scan(body, self.addr)
        scan, new = self._seq.poll(snap, host_time, sent=sent)
        if new:
            self._pending.append(scan)
        return scan

    def read_scans(self) -> list[Scan]:
        self._poll()
        out, self._pending = self._pending, []
        return out

    def snapshot(self) -> Scan:
        """Poll ``#AA`` (:meth:`~loopcal.drivers.base.DAQ.snapshot`)."""
        return self._poll()

    def read_channel(self, channel: int) -> int:
        """``#AAn``: one channel's code in the latest scan.

        Parameters
        ----------
        channel : int
            1..4.

        Returns
        -------
        int
            The channel's code in the module's latest scan, 0..4095, decoded by
            :func:`parse_channel`.

        Raises
        ------
        ValueError
            For a channel outside 1..4.
        DAQError
            As :meth:`transact`.
        """
        if not 1 <= channel <= ldq412.N_CHANNELS:
            raise ValueError(f"channel {channel} outside 1..{ldq412.N_CHANNELS}")
        return parse_channel(self._command("#", str(channel)), self.addr)

    def read_scan_rate(self) -> int:
        return parse_rate(parse_ack(self._command("$", "R"), self.addr))

    def _write_scan_rate(self, hz: int) -> None:
        payload = parse_ack(self._command("%", f"R{hz:04X}"), self.addr)
        if payload:
            raise DAQProtocolError(f"{self.url}: set scan rate: unexpected payload {payload!r}")
        self._seq.set_rate(hz)

    def clear_restart(self) -> bool:
        """The ASCII protocol cannot clear the restart flag.

        Returns
        -------
        bool
            False, always (no command is sent).
        """
        return False

    def close(self) -> None:
        self._closed = True
        self._drop()
