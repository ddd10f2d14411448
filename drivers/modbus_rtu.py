"""LDQ-412 over Modbus RTU on RS-485 (pymodbus ModbusSerialClient, RTU framer).

URL: ``modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1&parity=N&stopbits=1&fifo=1``
(datasheet defaults: 115200 baud, 8N1, unit 1), or ``modbus-rtu://HOST:PORT?unit=1`` for
a line behind a serial device server in raw TCP mode (:mod:`loopcal.drivers.url`).

An RTU answer carries no transaction id: nothing in it says which request it answers.
The driver therefore has one request on the line at a time, and a request given up on
unanswered (:mod:`loopcal.drivers.modbus`) keeps the line until its answer came (drained
and discarded) or can no longer come: :data:`LATE_ANSWER_S` after it went out (or the
timeout, if longer; a FIFO read waits longer still for its own answer). A module that
answers each request at most once, within that time, never has an answer taken for
another request's. Beyond it, an answer of another shape (function, length, echo) is
refused, and so is a snapshot whose counter is behind the newest scan known without the
restart flag, which a power-on sets.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import ClassVar, Unpack

import serial
from pymodbus.client import ModbusSerialClient
from pymodbus.client.base import ModbusBaseSyncClient
from pymodbus.framer import FramerRTU, FramerType

from . import ldq412
from .errors import DAQDisconnected, DAQProtocolError, DAQTimeout
from .lines import bytes_waiting
from .modbus import FC_WRITE_SINGLE, ModbusDAQ, ModbusOptions
from .sequence import RawSnapshot, signed_delta
from .url import DaqUrl, line_url, serial_options

#: silence on the line that ends a drain after an error, s (many RTU frame times)
QUIET_S = 0.005
#: the latest an answer may come and still be waited out, s after its request: the line
#: is kept that long for a request given up on (the datasheet: answers within 5 ms, a
#: host's timeout 100 ms; modules and USB adapters were measured up to 400 ms late)
LATE_ANSWER_S = 0.5
#: bytes of an RTU answer besides its data: unit, function, byte count, CRC (2)
_RTU_OVERHEAD = 5


def holds_answer(data: bytes, unit: int) -> bool:
    """Whether bytes heard on the line hold a whole Modbus RTU answer from ``unit``.

    Parameters
    ----------
    data : bytes
        What was read, in order (noise and parts of frames around it allowed).
    unit : int
        The module's unit id.

    Returns
    -------
    bool
        True if some run of the bytes is an exception answer, a read answer (function 03
        or 04, its byte count's worth of data) or a write echo (06), its CRC right.
    """
    for i in range(len(data) - 1):
        if data[i] != unit:
            continue
        fc = data[i + 1]
        if fc & 0x80:
            size = _RTU_OVERHEAD
        elif fc == FC_WRITE_SINGLE:
            size = 8
        elif i + 2 < len(data):
            size = _RTU_OVERHEAD + data[i + 2]
        else:
            continue
        frame = data[i : i + size]
        if len(frame) == size and FramerRTU.check_CRC(frame[:-2], frame[-2] << 8 | frame[-1]):
            return True
    return False


class _SerialClient(ModbusSerialClient):
    """pymodbus' serial client whose ``connect`` raises the port's error (pyserial's
    SerialException, an OSError) where pymodbus' logs it and returns False: the driver's
    DAQDisconnected then carries it, and a device server's TCP port that refuses or cannot
    be reached is told from one that does not answer (:mod:`loopcal.drivers.diagnosis`).
    The port is opened as pymodbus opens it."""

    def connect(self) -> bool:
        if self.socket:
            return True
        params = self.comm_params
        try:
            self.socket = serial.serial_for_url(
                params.host, timeout=params.timeout_connect,
                write_timeout=params.timeout_connect, bytesize=params.bytesize,
                stopbits=params.stopbits, baudrate=params.baudrate, parity=params.parity,
                exclusive=True,
            )  # fmt: skip
        except Exception as exc:  # pyserial lets termios.error and ValueError through too
            if isinstance(exc, OSError):
                raise
            raise serial.SerialException(f"could not open port {params.host}: {exc}") from exc
        self.socket.inter_byte_timeout = self.inter_byte_timeout
        return True

    def _in_waiting(self) -> int:
        return bytes_waiting(self.socket) if self.socket is not None else 0


class ModbusRtuDAQ(ModbusDAQ):
    """LDQ-412 on RS-485,
    ``modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1&parity=N&stopbits=1&fifo=1``.

    RTU has no transaction id, so after an error the port is reopened and the line
    drained until ``QUIET_S`` of silence before the next request, and after a request
    given up on unanswered no request goes out until its late answer came or can no
    longer come (module docstring): a call meanwhile drains the line for at most the
    timeout and raises DAQTimeout. So a call spends at most the timeout on the line and
    the timeout on its answer (plus the transfer; a FIFO read longer, as
    :class:`~loopcal.drivers.modbus.ModbusDAQ`'s). A late answer costs the requests that
    could not go out meanwhile (the FIFO keeps the scans); a module that does not answer
    at all is asked again only once that time has passed.

    Parameters
    ----------
    port : str
        Serial device, e.g. ``"/dev/ttyUSB0"``, or a pyserial URL: a serial device
        server's TCP port is ``"socket://HOST:PORT"`` (its baud rate, parity and stop bits
        are the device server's settings; pyserial ignores these arguments on it).
    baud : int
        Line speed, baud (> 0; default 115200).
    parity : {"N", "E", "O"}
        Parity (default none).
    stopbits : {1, 2}
        Stop bits (default 1).
    **options
        ``unit``, ``timeout``, ``use_fifo``, ``check_identity``: as
        :class:`~loopcal.drivers.modbus.ModbusDAQ`'s.

    Raises
    ------
    ValueError
        For a parity, stop bits or baud out of range; a unit as
        :class:`~loopcal.drivers.modbus.ModbusDAQ`.
    DAQError
        If the port cannot be opened, or as :class:`~loopcal.drivers.modbus.ModbusDAQ`.

    Attributes
    ----------
    late_answers_discarded : int
        Answers that came after their request was given up on, drained and discarded.
    """

    scheme: ClassVar[str] = "modbus-rtu"
    url_params: ClassVar[frozenset[str]] = ModbusDAQ.url_params | {"baud", "parity", "stopbits"}

    def __init__(
        self,
        port: str,
        *,
        baud: int = ldq412.SERIAL_BAUD,
        parity: str = "N",
        stopbits: int = 1,
        **options: Unpack[ModbusOptions],
    ) -> None:
        if parity not in ("N", "E", "O"):
            raise ValueError(f"parity {parity!r} not N, E or O")
        if stopbits not in (1, 2):
            raise ValueError(f"stopbits {stopbits} not 1 or 2")
        if baud <= 0:
            raise ValueError(f"baud {baud} must be > 0")
        self.port, self.baud, self.parity, self.stopbits = port, baud, parity, stopbits
        self.late_answers_discarded = 0
        self._suspect: RawSnapshot | None = None  # the last snapshot refused as stale
        self._heard = bytearray()  # drained while the line is kept for a late answer
        super().__init__(line_url("modbus-rtu", port), {"baud": baud}, **options)

    @classmethod
    def url_options(cls, url: DaqUrl) -> dict[str, object]:
        return {
            **serial_options(url, "modbus-rtu:///dev/ttyUSB0"),
            **ModbusDAQ.common_options(url),
        }

    def _make_client(self, trace: Callable[[bool, bytes], bytes]) -> ModbusBaseSyncClient:
        return _SerialClient(
            self.port,
            framer=FramerType.RTU,
            baudrate=self.baud,
            bytesize=8,
            parity=self.parity,
            stopbits=self.stopbits,
            timeout=self.timeout,
            retries=0,
            trace_packet=trace,
        )

    def _resync(self) -> None:
        """Reopen the port; drain the line until it is quiet and no answer to a request
        given up on can still come (class docstring), for at most the timeout.

        Raises
        ------
        DAQTimeout
            If a late answer may still come when the timeout is up (the next call goes on
            waiting for it).
        DAQDisconnected
            If the port does not open (the next call tries again).
        """
        client = self._client
        try:
            client.connect()
        except OSError as exc:
            self._resync_needed = True
            raise DAQDisconnected(f"{self.url}: cannot connect: {exc}") from exc
        ser = client.socket
        awaited = self._unanswered_at
        kept_until = 0.0 if awaited is None else awaited + max(LATE_ANSWER_S, self.timeout)
        heard = self._heard  # since the request given up on: its answer may span two calls
        now = last_rx = time.monotonic()
        deadline = now + self.timeout
        try:
            while now < deadline:
                if waiting := bytes_waiting(ser):
                    heard += ser.read(waiting)
                    last_rx = now
                elif now - last_rx >= QUIET_S and (
                    now >= kept_until or holds_answer(bytes(heard), self.unit)
                ):
                    break
                time.sleep(0.001)
                now = time.monotonic()
        except OSError:
            self._drop()
            return
        answered = awaited is not None and holds_answer(bytes(heard), self.unit)
        if not answered and now < kept_until:
            self._resync_needed = True
            raise DAQTimeout(
                f"{self.url}: the line is kept {kept_until - now:.2f} s more for the late "
                f"answer to a request given up on (an RTU answer names no request)"
            )
        self.late_answers_discarded += answered
        self._unanswered_at = None
        heard.clear()

    def _read_snapshot(self) -> tuple[RawSnapshot, float]:
        """The snapshot, refused (DAQProtocolError) when its counter is behind the newest
        scan known without the restart flag: a power-on sets the flag, so it is an earlier
        request's late answer. A second such snapshot in a row, the module moved on from
        the first, is taken for what it is: a restart whose flag another master cleared."""
        snap, host_time = super()._read_snapshot()
        suspect, self._suspect = self._suspect, None
        restarted = snap.status & ldq412.STATUS_RESTART
        if restarted or not self._seq.goes_back(snap.counter):
            return snap, host_time
        if suspect is not None and signed_delta(snap.counter, suspect.counter) >= 0:
            return snap, host_time
        self._suspect = snap
        self._drop(unanswered=True)
        raise DAQProtocolError(
            f"{self.url}: snapshot of scan {snap.counter}, behind the newest known, without "
            f"the restart flag: an earlier request's late answer, discarded"
        )
