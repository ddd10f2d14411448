"""Register-map logic shared by the Modbus TCP and Modbus RTU drivers.

Transport details (framing, CRC, MBAP, sockets, serial ports) are pymodbus's; this module
only knows the LDQ-412 register map and turns pymodbus outcomes into DAQError subclasses.

Retry policy: pymodbus retries are 0. A FIFO read is destructive (the module removes the
scans it answers with), so resending a request whose answer was lost or corrupted would
silently skip scans; instead the call raises, and the scans lost with the answer show up
as Scan.missed on the next scan delivered. A dead device therefore costs one timeout per
call, never more (plus the answer's transfer time), except the FIFO window read: that
read is made just after the snapshot answered, and giving up on it loses the scans it
carries, so its answer is waited for longer (:data:`FIFO_ANSWER_WAIT_S`, at most half the
FIFO's depth in time): a module or network slower than the datasheet's 100 ms, now and
then, costs no scan (counted in :attr:`ModbusDAQ.late_fifo_answers`).

After a timeout or a protocol error the connection is dropped and reopened on the next
call (TCP: a fresh socket, so a late answer can never be taken for the next one; RTU, which
has no transaction id: the port is reopened, and no request goes out while the answer to
one given up on may still come, :class:`~loopcal.drivers.modbus_rtu.ModbusRtuDAQ`). A
request is given up on *unanswered* when nothing came, or an answer that cannot be its
own (another function, length or echo, a snapshot out of range): its own may still come.

FIFO overflow: the driver never writes holding register 2, since by the datasheet that
clears the FIFO along with the overflow flag, and would throw away the scans that arrived
while the driver was reading. The flag stays latched; an overflow shows as a counter gap
in the FIFO (the oldest scans were dropped) after the module made a FIFO's worth of
scans, told apart from a FIFO answer lost on the way (the driver knows which reads
failed) and from scans another Modbus master took off the FIFO (a gap neither explains).
See :class:`loopcal.drivers.sequence.Sequencer`.

Modules differ where the datasheet is loose (docs/daq.md, "open points"): a FIFO answer
with fewer scans than asked (a module that leaves the filler out, or truncates long
reads) is accepted; a module that refuses 20-scan reads (exception 02 or 03) is read in smaller
chunks, which is safe because a refused read takes nothing off the FIFO.
"""

from __future__ import annotations

import time
from abc import abstractmethod
from collections.abc import Callable
from typing import ClassVar, TypedDict

from pymodbus.client.base import ModbusBaseSyncClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ExceptionResponse, ModbusPDU

from . import ldq412
from .base import DAQ, Identity, Scan
from .errors import (
    DAQDisconnected,
    DAQError,
    DAQIdentityError,
    DAQModbusException,
    DAQProtocolError,
    DAQTimeout,
)
from .sequence import RawSnapshot
from .url import DaqUrl

#: s a FIFO window read waits for its answer (at most half the FIFO's depth in time at the
#: module's rate, at least the timeout): a late answer still carries its scans
FIFO_ANSWER_WAIT_S = 2.5

FC_READ_HOLDING = 3
FC_READ_INPUT = 4
FC_WRITE_SINGLE = 6


def parse_snapshot(regs: list[int]) -> RawSnapshot:
    """Decode the snapshot, input registers 0..9.

    Parameters
    ----------
    regs : list of int
        The 10 registers, 16-bit each.

    Returns
    -------
    RawSnapshot
        Counter, time, codes, status and FIFO level of the latest scan.

    Raises
    ------
    DAQProtocolError
        For another number of registers, a code above 4095 or a FIFO level above 256.
    """
    if len(regs) != ldq412.IR_SNAPSHOT_LEN:
        raise DAQProtocolError(f"snapshot: {len(regs)} registers, expected 10")
    codes = (regs[4], regs[5], regs[6], regs[7])
    if max(codes) > ldq412.CODE_MAX:
        raise DAQProtocolError(f"snapshot: code out of range in {codes}")
    level = regs[ldq412.IR_FIFO_LEVEL]
    if level > ldq412.FIFO_DEPTH:
        raise DAQProtocolError(f"snapshot: FIFO level {level} > {ldq412.FIFO_DEPTH}")
    return RawSnapshot(
        counter=ldq412.join_u32(regs[0], regs[1]),
        time_us=ldq412.join_u32(regs[2], regs[3]),
        codes=codes,
        status=regs[ldq412.IR_STATUS],
        fifo_level=level,
    )


def parse_fifo(regs: list[int]) -> tuple[list[tuple[int, tuple[int, int, int, int]]], int]:
    """Decode a FIFO answer, input registers 256.. (six per scan).

    Parameters
    ----------
    regs : list of int
        The registers answered, 16-bit each: counter hi, counter lo, ch1..ch4 per scan.

    Returns
    -------
    scans : list of (int, tuple of 4 int)
        ``(counter, codes)`` per scan, oldest first, filler scans dropped.
    filler : int
        Filler scans (six 0xFFFF registers) at the end: the FIFO ran empty.

    Raises
    ------
    DAQProtocolError
        If the registers are not whole scans, a scan has a code above 4095 (a partly
        filled scan, corrupted data), or a scan follows a filler scan.
    """
    n = ldq412.FIFO_SCAN_REGS
    if len(regs) % n:
        raise DAQProtocolError(f"FIFO: {len(regs)} registers is not a whole number of scans")
    out: list[tuple[int, tuple[int, int, int, int]]] = []
    filler = 0
    for i in range(0, len(regs), n):
        hi, lo, c1, c2, c3, c4 = regs[i : i + n]
        if c1 == c2 == c3 == c4 == hi == lo == ldq412.FIFO_FILLER:
            filler += 1
            continue
        if filler:
            raise DAQProtocolError(f"FIFO: a scan after a filler scan in {regs}")
        codes = (c1, c2, c3, c4)
        if max(codes) > ldq412.CODE_MAX:
            raise DAQProtocolError(f"FIFO: malformed scan {regs[i : i + n]}")
        out.append((ldq412.join_u32(hi, lo), codes))
    return out, filler


def format_firmware(reg: int) -> str:
    """The firmware version in input register 513.

    Parameters
    ----------
    reg : int
        ``major * 256 + minor``.

    Returns
    -------
    str
        ``"M.mm"``, e.g. ``"2.01"`` for 0x0201.
    """
    return f"{reg >> 8}.{reg & 0xFF:02d}"


class ModbusOptions(TypedDict, total=False):
    """The keyword arguments every Modbus driver takes (:class:`ModbusDAQ` holds their
    defaults).

    Attributes
    ----------
    unit : int
        The module's Modbus unit id, 1..247.
    timeout : float
        s to wait for an answer.
    use_fifo : bool
        Read the module's FIFO (True) or poll its latest scan.
    check_identity : bool
        Refuse a module that does not say it is an LDQ-412.
    """

    unit: int
    timeout: float
    use_fifo: bool
    check_identity: bool


class ModbusDAQ(DAQ):
    """LDQ-412 over Modbus (TCP or RTU): the register map, FIFO draining, flag clearing.

    Abstract: :class:`~loopcal.drivers.modbus_tcp.ModbusTcpDAQ` and
    :class:`~loopcal.drivers.modbus_rtu.ModbusRtuDAQ` give it a pymodbus client. URL
    parameters common to both: ``unit`` (Modbus device id, default 1), ``fifo`` (1:
    read_scans drains the FIFO, the default; 0: it polls the snapshot, e.g. when another
    master owns the FIFO).

    Parameters
    ----------
    link : str
        The URL up to its query: the scheme and where the module is, e.g.
        ``"modbus-tcp://10.0.0.7:502"``.
    link_params : dict[str, object]
        The transport's own URL parameters, in the order the URL writes them.
    unit : int
        Modbus device id, 0..247 (0 broadcast; the URL takes 1..247; default 1).
    timeout : float
        s without an answer before a call raises DAQTimeout (default 0.1).
    use_fifo : bool
        Drain the FIFO (True, the default) or poll the snapshot (False).
    check_identity : bool
        Raise DAQIdentityError unless the model code is 0x0412 (default True).

    Attributes
    ----------
    fifo_chunk : int
        Scans per FIFO read: the datasheet's 20, fewer once a module refused a read
        of that many or truncated two reads in a row to the same fewer.
    late_fifo_answers : int
        FIFO reads answered after ``timeout`` but within :data:`FIFO_ANSWER_WAIT_S`
        (their scans kept).

    Raises
    ------
    ValueError
        If ``unit`` is outside 0..247.
    DAQError
        If the module cannot be reached or read at connect, or is not an LDQ-412.
    """

    url_params: ClassVar[frozenset[str]] = frozenset({"unit", "fifo"})

    @staticmethod
    def common_options(url: DaqUrl) -> dict[str, object]:
        """The Modbus URL parameters both transports take, checked.

        Parameters
        ----------
        url : DaqUrl
            A ``modbus-tcp`` or ``modbus-rtu`` URL.

        Returns
        -------
        dict[str, object]
            ``unit`` (1..247, default 1) and ``use_fifo`` (from ``fifo`` 0/1, default 1).

        Raises
        ------
        ValueError
            For a value out of range, naming the URL.
        """
        return {
            "unit": url.get_int("unit", ldq412.MODBUS_UNIT, lo=1, hi=247),
            "use_fifo": url.get_bool("fifo", True),
        }

    def __init__(
        self,
        link: str,
        link_params: dict[str, object],
        *,
        unit: int = ldq412.MODBUS_UNIT,
        timeout: float = ldq412.HOST_TIMEOUT_S,
        use_fifo: bool = True,
        check_identity: bool = True,
    ) -> None:
        if not 0 <= unit <= 247:
            raise ValueError(f"Modbus unit {unit} outside 0..247")
        params = {**link_params, "unit": unit, "fifo": int(use_fifo)}
        #: the connection's URL, every parameter written out (for messages)
        self.url = f"{link}?" + "&".join(f"{k}={v}" for k, v in params.items())
        self.unit = unit
        self.timeout = timeout
        self.use_fifo = use_fifo
        self._rx_bytes = 0
        self._closed = False
        self._resync_needed = False
        #: monotonic time the latest request went out, s
        self._sent_at = 0.0
        #: when the latest request given up on unanswered went out (its answer may still
        #: come; the RTU line is kept for it), or None
        self._unanswered_at: float | None = None
        self._pending: list[Scan] = []
        # scans per FIFO read: the datasheet's 20, fewer for a module that refuses that
        self.fifo_chunk = ldq412.FIFO_MAX_SCANS_PER_READ
        self.late_fifo_answers = 0
        self._client = self._make_client(self._trace_packet)
        self._connect_and_identify(self._connect, check_identity)

    # -- transport hooks -----------------------------------------------------------------

    @abstractmethod
    def _make_client(self, trace: Callable[[bool, bytes], bytes]) -> ModbusBaseSyncClient:
        """A pymodbus sync client with retries=0, timeout=self.timeout, trace_packet=trace."""

    def _resync(self) -> None:
        """Bring the link back to a known state after an error (transport specific), or
        raise a DAQError if no request may go out yet."""

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending:
            self._sent_at = time.monotonic()
        else:
            self._rx_bytes += len(data)
        return data

    def _connect(self) -> None:
        try:
            ok = self._client.connect()
        except (OSError, ModbusException) as exc:
            raise DAQDisconnected(f"{self.url}: cannot connect: {exc}") from exc
        if not ok:
            raise DAQDisconnected(f"{self.url}: cannot connect")

    def _drop(self, *, unanswered: bool = False) -> None:
        """Close the link after an error; the next call reopens it (:meth:`_resync`).
        ``unanswered``: the request's own answer may still come (module docstring)."""
        self._resync_needed = True
        if unanswered:
            self._unanswered_at = self._sent_at
        try:
            self._client.close()
        except Exception:  # noqa: BLE001 - closing a broken transport must not raise
            pass

    def _execute(self, what: str, fc: int, op: Callable[[], ModbusPDU]) -> ModbusPDU:
        """Run one pymodbus request, mapping every outcome onto the typed errors."""
        if self._closed:
            raise DAQDisconnected(f"{self.url}: driver closed")
        if self._resync_needed:
            self._resync_needed = False
            self._resync()
        self._rx_bytes = 0
        try:
            rsp = op()
        except ConnectionException as exc:
            self._drop()
            raise DAQDisconnected(f"{self.url}: {what}: {exc}") from exc
        except ModbusIOException as exc:
            self._drop(unanswered=not self._rx_bytes)
            if self._rx_bytes:
                raise DAQProtocolError(
                    f"{self.url}: {what}: {self._rx_bytes} bytes received but no valid "
                    f"answer (garbage, partial frame or bad CRC/MBAP)"
                ) from exc
            waited = self._client.comm_params.timeout_connect
            raise DAQTimeout(f"{self.url}: {what}: no answer within {waited} s") from exc
        except (ModbusException, ValueError, IndexError) as exc:
            self._drop()
            raise DAQProtocolError(f"{self.url}: {what}: undecodable answer: {exc}") from exc
        except OSError as exc:
            self._drop()
            raise DAQDisconnected(f"{self.url}: {what}: {exc}") from exc
        if isinstance(rsp, ExceptionResponse):
            raise DAQModbusException(
                rsp.exception_code,
                fc,
                f"{self.url}: {what}: Modbus exception {rsp.exception_code:#04x}",
            )
        if rsp.function_code != fc:
            self._drop(unanswered=True)
            raise DAQProtocolError(
                f"{self.url}: {what}: answer has function {rsp.function_code}, expected {fc}"
            )
        return rsp

    # -- low-level register access (public: also for diagnostics) ------------------------

    def read_input_registers(self, address: int, count: int, *, step: int = 0) -> list[int]:
        """Read input registers (function 04); for diagnostics too.

        Parameters
        ----------
        address : int
            First register, zero-based.
        count : int
            Registers to read (1..125).
        step : int
            If > 0, a shorter answer of a multiple of ``step`` registers is accepted (a
            FIFO answer of fewer whole scans).

        Returns
        -------
        list of int
            The registers, 16-bit each.

        Raises
        ------
        DAQProtocolError
            If the answer has the wrong length, or is malformed.
        DAQModbusException
            If the module answered an exception (02: address, 03: value).
        DAQTimeout, DAQDisconnected
            No answer in time, or no connection.
        """
        return self._read_registers("input", address, count, step)

    def read_holding_registers(self, address: int, count: int) -> list[int]:
        """Read holding registers (function 03), as :meth:`read_input_registers` reads
        input registers: the same answer checked the same way, the same errors.

        Parameters
        ----------
        address : int
            First register, zero-based (0..4: scan rate, oversampling, clear FIFO, clear
            restart, ASCII checksum mode).
        count : int
            Registers to read.

        Returns
        -------
        list of int
            The registers.
        """
        return self._read_registers("holding", address, count)

    def _read_registers(self, kind: str, address: int, count: int, step: int = 0) -> list[int]:
        """``count`` registers of ``kind`` ("input": function 04, "holding": 03) from
        ``address``, the answer's length checked (``step``: :meth:`read_input_registers`)."""
        fc, read = {
            "input": (FC_READ_INPUT, self._client.read_input_registers),
            "holding": (FC_READ_HOLDING, self._client.read_holding_registers),
        }[kind]
        what = f"{kind} registers {address}+{count}"
        rsp = self._execute(
            f"read {what}", fc, lambda: read(address, count=count, device_id=self.unit)
        )
        regs = list(rsp.registers)
        short_ok = step and len(regs) < count and len(regs) % step == 0
        if len(regs) != count and not short_ok:
            self._drop(unanswered=True)
            raise DAQProtocolError(f"{self.url}: {what}: {len(regs)} registers answered")
        return regs

    def write_register(self, address: int, value: int) -> None:
        """Write one holding register (function 06).

        Parameters
        ----------
        address : int
            The register, zero-based.
        value : int
            0..65535.

        Raises
        ------
        DAQProtocolError
            Unless the module echoes the request.
        DAQModbusException, DAQTimeout, DAQDisconnected
            As :meth:`read_input_registers`.
        """
        rsp = self._execute(
            f"write register {address}={value}",
            FC_WRITE_SINGLE,
            lambda: self._client.write_register(address, value, device_id=self.unit),
        )
        if getattr(rsp, "address", None) != address or list(rsp.registers) != [value]:
            self._drop(unanswered=True)
            raise DAQProtocolError(f"{self.url}: write {address}={value}: wrong echo {rsp}")

    # -- device functions ----------------------------------------------------------------

    def _read_identity(self, check: bool) -> Identity:
        model, fw, ser_hi, ser_lo = self.read_input_registers(
            ldq412.IR_MODEL, ldq412.IR_IDENTITY_LEN
        )
        if check and model != ldq412.MODEL_CODE:
            raise DAQIdentityError(
                f"{self.url}: model code {model:#06x}, expected {ldq412.MODEL_CODE:#06x}"
            )
        name = ldq412.MODEL_NAME if model == ldq412.MODEL_CODE else f"unknown-{model:#06x}"
        return Identity(name, format_firmware(fw), ldq412.join_u32(ser_hi, ser_lo), model)

    def read_scan_rate(self) -> int:
        (rate,) = self.read_holding_registers(ldq412.HR_SCAN_RATE, 1)
        if not ldq412.SCAN_RATE_MIN_HZ <= rate <= ldq412.SCAN_RATE_MAX_HZ:
            raise DAQProtocolError(f"{self.url}: scan rate register reads {rate}")
        return rate

    def _fifo_answer_wait(self) -> float:
        """s to wait for a FIFO read's answer: FIFO_ANSWER_WAIT_S, at most half the FIFO's
        depth at the module's rate, never less than the timeout."""
        half_fifo = ldq412.FIFO_DEPTH / self.scan_rate_hz / 2
        return max(self.timeout, min(FIFO_ANSWER_WAIT_S, half_fifo))

    def _read_snapshot(self) -> tuple[RawSnapshot, float]:
        regs = self.read_input_registers(ldq412.IR_COUNTER, ldq412.IR_SNAPSHOT_LEN)
        host_time = time.monotonic()
        try:
            return parse_snapshot(regs), host_time
        except DAQProtocolError as exc:
            self._drop(unanswered=True)
            raise DAQProtocolError(f"{self.url}: {exc}") from None

    def _read_fifo(self, n: int) -> tuple[list[tuple[int, tuple[int, int, int, int]]], int, int]:
        """Up to ``n`` scans off the FIFO: (scans, filler scans, scans not answered at all).

        A module that refuses a read of ``n`` scans (02 or 03, nothing taken) is asked
        for half as many, and :attr:`fifo_chunk` remembers it. A read that fails on the
        way may have taken scans: the sequencer is told, so that the counter gap it
        leaves is not taken for an overflow.
        """
        per = ldq412.FIFO_SCAN_REGS
        params = self._client.comm_params
        while True:
            # pymodbus reads its timeout at each call: this one waits longer for its answer
            params.timeout_connect = self._fifo_answer_wait()
            sent = time.monotonic()
            try:
                regs = self.read_input_registers(ldq412.IR_FIFO, n * per, step=per)
                if time.monotonic() - sent > self.timeout:
                    self.late_fifo_answers += 1
                break
            except DAQModbusException as exc:
                if n == 1 or exc.code not in (exc.ILLEGAL_DATA_ADDRESS, exc.ILLEGAL_DATA_VALUE):
                    raise
                n = self.fifo_chunk = max(1, n // 2)
            except DAQError:
                self._seq.fifo_read_lost()
                raise
            finally:
                params.timeout_connect = self.timeout
        try:
            scans, filler = parse_fifo(regs)
        except DAQProtocolError as exc:
            self._seq.fifo_read_lost()
            self._drop(unanswered=True)
            raise DAQProtocolError(f"{self.url}: {exc}") from None
        return scans, filler, n - len(scans) - filler

    def _clear_restart_latch(self, status: int) -> None:
        if status & ldq412.STATUS_RESTART:
            self.write_register(ldq412.HR_CLEAR_RESTART, 1)
            self._seq.restart_bit_cleared()

    def _drain(self) -> list[Scan]:
        """One FIFO transaction: anchor snapshot, the waiting scans, restart-flag clearing.

        Reads the scans the snapshot's level says wait, in chunks, the last asking for
        one scan more (one that arrived meanwhile, else a filler scan or a short answer).
        Two reads in a row answered with the same fewer scans than asked, while more
        wait, make that number :attr:`fifo_chunk` (a module that truncates long reads).
        Scans that skip a counter are followed by another snapshot, whose counter tells
        an overflow while the FIFO was read from another master's reads
        (:meth:`Sequencer.gap_in <loopcal.drivers.sequence.Sequencer.gap_in>`).
        """
        snap, snap_time = self._read_snapshot()
        self._seq.begin_batch(snap, snap_time)
        if self._seq.period_mismatch():
            # Somebody changed the scan rate behind our back: derived times need the new one.
            self._seq.set_rate(self.read_scan_rate())
        raw: list[tuple[int, tuple[int, int, int, int]]] = []
        out: list[Scan] = []
        later: RawSnapshot | None = None
        arrived: float | None = None
        remaining = snap.fifo_level or 0
        short = 0  # scans in the previous read if it answered fewer than asked, more waiting
        try:
            while remaining > 0:
                n = min(self.fifo_chunk, remaining + 1)
                chunk, filler, unanswered = self._read_fifo(n)
                raw.extend(chunk)
                if filler or not chunk:
                    break  # the FIFO is empty
                remaining -= len(chunk)
                if unanswered and remaining > 0:
                    # Fewer answered than asked although the snapshot said more wait: a
                    # module's limit if the next read of more answers as many again; once
                    # may be a FIFO emptied since the snapshot (power cycle, other master).
                    if short == len(chunk):
                        self.fifo_chunk = short
                    short = len(chunk)
                else:
                    short = 0
            arrived = time.monotonic()
            if self._seq.gap_in(raw):
                # The module's counter now tells whether the FIFO overflowed while it was
                # read (its answers slow): the batch's own counters may not show it.
                later = self._read_snapshot()[0]
        finally:
            # Scans taken off the device are never dropped, even if a later read failed.
            if raw:
                out = self._seq.fifo_scans(raw, arrived or time.monotonic(), later)
                self._pending.extend(out)
        self._clear_restart_latch(snap.status)
        return out

    def _poll(self) -> Scan:
        snap, host_time = self._read_snapshot()
        scan, new = self._seq.poll(snap, host_time)
        if new:
            self._pending.append(scan)
        self._clear_restart_latch(snap.status)
        return scan

    def read_scans(self) -> list[Scan]:
        if self.use_fifo:
            self._drain()
        else:
            self._poll()
        out, self._pending = self._pending, []
        return out

    @property
    def has_fifo(self) -> bool:
        return self.use_fifo

    def snapshot(self) -> Scan:
        if not self.use_fifo:
            return self._poll()
        snap, host_time = self._read_snapshot()
        return self._seq.peek(snap, host_time)

    def _write_scan_rate(self, hz: int) -> None:
        if self.use_fifo:
            # FIFO scans' times are derived from the rate: take the old-rate ones first.
            self._drain()
        self.write_register(ldq412.HR_SCAN_RATE, hz)
        self._seq.set_rate(hz)

    def read_oversampling(self) -> int:
        """Conversions averaged per reported code, read from the module (holding
        register 1; a request on the wire). Read with register 0, the scan rate: a
        two-register answer, never taken for a :meth:`read_scan_rate`'s over RTU, whose
        answers carry no request id.

        Returns
        -------
        int
            1, 2, 4, 8 or 16.

        Raises
        ------
        DAQError
            If the module cannot be read.
        """
        regs = self.read_holding_registers(ldq412.HR_SCAN_RATE, ldq412.HR_OVERSAMPLING + 1)
        return regs[ldq412.HR_OVERSAMPLING]

    def write_oversampling(self, n: int) -> None:
        """Set the conversions averaged per reported code (holding register 1; a write on
        the wire).

        Parameters
        ----------
        n : int
            1, 2, 4, 8 or 16.

        Raises
        ------
        ValueError
            When ``n`` is another number (nothing is written).
        DAQError
            If the module cannot be written.
        """
        if n not in ldq412.OVERSAMPLING_CHOICES:
            raise ValueError(f"oversampling {n} not in {ldq412.OVERSAMPLING_CHOICES}")
        self.write_register(ldq412.HR_OVERSAMPLING, n)

    def clear_fifo(self) -> None:
        """Empty the module's FIFO and clear its overflow flag (holding register 2): the
        scans in it are lost, and reported as missed (as a lost answer's are, not as
        another reader's). read_scans never does this.

        Raises
        ------
        DAQError
            If the module cannot be written.
        """
        self._seq.fifo_read_lost()  # the gap it leaves is ours, whether the write answers or not
        self.write_register(ldq412.HR_CLEAR_FIFO, 1)

    def clear_restart(self) -> bool:
        # Observe the flag first, so clearing it never hides a restart from read_scans.
        if self.use_fifo:
            self._drain()
        else:
            self._poll()
        self.write_register(ldq412.HR_CLEAR_RESTART, 1)
        self._seq.restart_bit_cleared()
        return True

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._client.close()
        except Exception:  # noqa: BLE001
            pass
