"""The LDQ-412's register map (docs/daq.md, "Modbus"): how Modbus reads and writes see
the device model's state, and the exception each refusal answers.

:class:`ModbusRegisters` is a part of :class:`~loopcal.simulator.device.LDQ412` (its base
class): the model keeps the state (scans, FIFO, latches, settings) and its timing; these
methods are the datasheet's register tables over it, the open points included (a module
that truncates long reads, answers holes with zeros, or refuses part of the snapshot:
:mod:`loopcal.simulator.open_points`). The ASCII protocol reads the same state through
the model's properties (:mod:`loopcal.simulator.ascii_protocol`).
"""

from __future__ import annotations

import collections
from typing import Any

from loopcal.drivers.ldq412 import (
    FIFO_FILLER,
    FIFO_MAX_SCANS_PER_READ,
    FIFO_SCAN_REGS,
    HR_ASCII_CHECKSUM,
    HR_CLEAR_FIFO,
    HR_CLEAR_RESTART,
    HR_COUNT,
    HR_OVERSAMPLING,
    HR_SCAN_RATE,
    IR_FIFO,
    IR_FIFO_END,
    IR_IDENTITY_LEN,
    IR_MODEL,
    IR_SNAPSHOT_LEN,
    MODEL_CODE,
    OVERSAMPLING_CHOICES,
    SCAN_RATE_MAX_HZ,
    SCAN_RATE_MIN_HZ,
    split_u32,
)

from .open_points import MODBUS_MAX_READ, OpenPoints

# Modbus exception codes the module answers (datasheet: 02 and 03; 01 for functions it
# does not implement).
ILLEGAL_FUNCTION = 0x01  #: Modbus exception 01, illegal function
ILLEGAL_ADDRESS = 0x02  #: Modbus exception 02, illegal data address
ILLEGAL_VALUE = 0x03  #: Modbus exception 03, illegal data value

# Protocol limit of a single Modbus register write (Modbus application spec; the read's,
# MODBUS_MAX_READ, is in open_points).
MODBUS_MAX_WRITE = 123
_IR_MAP_END = IR_MODEL + IR_IDENTITY_LEN  # one past the last input register


class DeviceError(Exception):
    """A request the module refuses with a Modbus exception code.

    The Modbus servers answer it as that exception; the ASCII protocol as ``?AA``.

    Parameters
    ----------
    code : int
        The exception code: 0x01 illegal function, 0x02 illegal data address, 0x03
        illegal data value (:data:`ILLEGAL_FUNCTION`, :data:`ILLEGAL_ADDRESS`,
        :data:`ILLEGAL_VALUE`).
    message : str
        Why, for people; the exception's text is ``exception CC: message``.

    Attributes
    ----------
    code : int
        As given.
    """

    def __init__(self, code: int, message: str) -> None:
        super().__init__(f"exception {code:02X}: {message}")
        self.code = code


class ModbusRegisters:
    """Functions 03, 04, 06 and 16 over the device model's state (module docstring)."""

    # the model's state these methods read and write (loopcal.simulator.device.LDQ412)
    open: OpenPoints
    firmware: tuple[int, int]
    serial_number: int
    fifo_reads: int
    _fifo: collections.deque
    _scan_rate: int
    _oversampling: int
    _ascii_checksum: bool
    _overflow: bool
    _restart: bool

    latest: Any  # a TruthScan (the latest scan)
    status: int

    # the model's own (LDQ412 defines both): a subclass without them fails loudly, not silently
    def _require_power(self) -> None:
        raise NotImplementedError

    def set_scan_rate(self, rate_hz: int) -> None:
        raise NotImplementedError

    def _check_request(self, count: int, limit: int) -> None:
        """What every register request passes first: the power (DeviceOffError), then
        its count, 1..``limit`` (03)."""
        self._require_power()
        if not 1 <= count <= limit:
            raise DeviceError(ILLEGAL_VALUE, f"count {count} outside 1..{limit}")

    def snapshot_registers(self) -> list[int]:
        """Input registers 0..9: one consistent view of the latest scan.

        Returns
        -------
        list of int
            Ten 16-bit registers: counter (hi, lo), device time in µs (hi, lo), channel
            1..4 codes, status, FIFO level.

        Raises
        ------
        DeviceOffError
            While the module is not :attr:`ready`.
        """
        s = self.latest
        return [
            *split_u32(s.counter),
            *split_u32(s.time_us),
            *s.codes,
            self.status,
            len(self._fifo),
        ]

    def identity_registers(self) -> list[int]:
        """Input registers 512..515: model, firmware, serial number.

        Returns
        -------
        list of int
            Four 16-bit registers: model code 0x0412, ``major * 256 + minor``, serial
            number (hi, lo).
        """
        major, minor = self.firmware
        return [MODEL_CODE, major * 256 + minor, *split_u32(self.serial_number)]

    def read_input_registers(self, address: int, count: int) -> list[int]:
        """Function 04, read input registers (a FIFO-window read pops its scans).

        Parameters
        ----------
        address : int
            First register, zero-based.
        count : int
            Registers asked for.

        Returns
        -------
        list of int
            The 16-bit registers: ``count`` of them, or fewer for a truncated read
            (``over_limit="truncate"``) or a short FIFO answer (``fifo_underrun="short"``).

        Raises
        ------
        DeviceError
            03 for a count outside 1..125 or a FIFO-window read whose count is not a
            multiple of 6; 02 for addresses outside 0..9, 256..375, 512..515, a
            FIFO-window read not starting at 256 or reading past 375 (more than 20
            scans). The open points change these answers (Notes).
        DeviceOffError
            While the module is not :attr:`ready`.

        Notes
        -----
        ``max_read_registers`` below 125 refuses a longer read with 03
        (``over_limit="refuse"``) or answers its first ``max_read_registers`` registers
        (``"truncate"``; in the FIFO window whole scans only, the rest left waiting);
        ``holes="zero"`` answers a read that leaves the listed blocks (unlisted registers
        0, the FIFO window 0xFFFF without taking a scan); ``snapshot_reads="whole"``
        refuses a read of part of 0..9 with 02 (:mod:`loopcal.simulator.open_points`).
        """
        self._check_request(count, MODBUS_MAX_READ)
        op = self.open
        if count > op.max_read_registers:
            if op.over_limit == "refuse":
                raise DeviceError(
                    ILLEGAL_VALUE, f"count {count} over this module's {op.max_read_registers}"
                )
            count = op.max_read_registers
            if address == IR_FIFO:  # whole scans only; the rest stays waiting
                count -= count % FIFO_SCAN_REGS
                if not count:
                    raise DeviceError(ILLEGAL_VALUE, "not one whole FIFO scan fits a read")
        end = address + count
        if 0 <= address and end <= IR_SNAPSHOT_LEN:
            if op.snapshot_reads == "whole" and (address, count) != (0, IR_SNAPSHOT_LEN):
                raise DeviceError(ILLEGAL_ADDRESS, "the snapshot is read whole (0..9)")
            return self.snapshot_registers()[address:end]
        if IR_MODEL <= address and end <= _IR_MAP_END:
            return self.identity_registers()[address - IR_MODEL : end - IR_MODEL]
        if address == IR_FIFO and end <= IR_FIFO_END:
            if count % FIFO_SCAN_REGS:
                raise DeviceError(ILLEGAL_VALUE, f"FIFO read of {count} registers, not N*6")
            return self.pop_fifo(count // FIFO_SCAN_REGS)
        if op.holes == "zero" and 0 <= address and end <= _IR_MAP_END:
            return self._read_across_holes(address, end)
        raise DeviceError(ILLEGAL_ADDRESS, f"input registers {address}..{end - 1}")

    def _read_across_holes(self, address: int, end: int) -> list[int]:
        """A read that leaves the listed blocks, on a module that answers it: unlisted
        registers read 0, the snapshot and identity their values, and the FIFO window
        (not read from its start) 0xFFFF without taking any scan."""
        snap = self.snapshot_registers() if address < IR_SNAPSHOT_LEN else []
        ident = self.identity_registers() if end > IR_MODEL else []
        out = []
        for a in range(address, end):
            if a < IR_SNAPSHOT_LEN:
                out.append(snap[a])
            elif IR_FIFO <= a < IR_FIFO_END:
                out.append(FIFO_FILLER)
            elif a >= IR_MODEL:
                out.append(ident[a - IR_MODEL])
            else:
                out.append(0)
        return out

    def pop_fifo(self, n: int) -> list[int]:
        """Remove the ``n`` oldest scans; registers as the FIFO window returns them.

        Counts as a host's FIFO read (:attr:`fifo_reads`), whether any scan was waiting or
        not.

        Parameters
        ----------
        n : int
            Scans to take, 1..20.

        Returns
        -------
        list of int
            Six registers per scan (counter hi, counter lo, channel 1..4 codes), oldest
            first. Missing scans (fewer than ``n`` waiting) are all-0xFFFF filler scans,
            or left out (``fifo_underrun="short"``: the answer is shorter).

        Raises
        ------
        DeviceError
            03 for ``n`` outside 1..20.
        """
        if not 1 <= n <= FIFO_MAX_SCANS_PER_READ:
            raise DeviceError(ILLEGAL_VALUE, f"{n} scans per FIFO read")
        self.fifo_reads += 1
        regs: list[int] = []
        for _ in range(n):
            if self._fifo:
                counter, *codes = self._fifo.popleft()
                regs += [*split_u32(counter), *codes]
            elif self.open.fifo_underrun == "short":
                break
            else:
                regs += [FIFO_FILLER] * FIFO_SCAN_REGS
        return regs

    def holding_registers(self) -> list[int]:
        """Holding registers 0..4 as read.

        Returns
        -------
        list of int
            Scan rate (Hz), oversampling, 0, 0 (the command registers 2 and 3 read 0),
            ASCII checksum mode (0 or 1).
        """
        return [self._scan_rate, self._oversampling, 0, 0, int(self._ascii_checksum)]

    def read_holding_registers(self, address: int, count: int) -> list[int]:
        """Function 03, read holding registers: ``count`` registers of
        :meth:`holding_registers` from ``address`` (as :meth:`read_input_registers` takes
        them).

        Raises
        ------
        DeviceError
            03 for a count outside 1..125, 02 for registers outside 0..4.
        DeviceOffError
            While the module is not :attr:`ready`.
        """
        self._check_request(count, MODBUS_MAX_READ)
        _check_holding_span(address, count)
        return self.holding_registers()[address : address + count]

    def write_registers(self, address: int, values: list[int]) -> None:
        """Functions 06 and 16, write holding registers (every value checked first).

        Values are applied in address order: 0 sets the scan rate (:meth:`set_scan_rate`),
        1 the oversampling, 1 written to 2 clears the FIFO and the overflow flag, 1
        written to 3 clears the restart flag, 4 sets the ASCII checksum mode.

        Parameters
        ----------
        address : int
            First register, zero-based.
        values : list of int
            The 16-bit values, one per register from ``address``.

        Raises
        ------
        DeviceError
            02 for registers outside 0..4; 03 for a count outside 1..123 or a value out
            of range: rate 1..200, oversampling 1/2/4/8/16, command registers 2 and 3
            take 0 (no-op) or 1, checksum mode 0 or 1. Nothing is applied then.
        DeviceOffError
            While the module is not :attr:`ready`.
        """
        self._check_request(len(values), MODBUS_MAX_WRITE)
        _check_holding_span(address, len(values))
        for reg, value in enumerate(values, start=address):
            if not _holding_value_ok(reg, value):
                raise DeviceError(ILLEGAL_VALUE, f"holding register {reg} = {value}")
        for reg, value in enumerate(values, start=address):
            if reg == HR_SCAN_RATE:
                self.set_scan_rate(value)
            elif reg == HR_OVERSAMPLING:
                self._oversampling = value
            elif reg == HR_CLEAR_FIFO and value == 1:
                self._fifo.clear()
                self._overflow = False
            elif reg == HR_CLEAR_RESTART and value == 1:
                self._restart = False
            elif reg == HR_ASCII_CHECKSUM:
                self._ascii_checksum = bool(value)


def _check_holding_span(address: int, count: int) -> None:
    """A read or write of ``count`` holding registers from ``address`` stays in 0..4 (02)."""
    if not (0 <= address and address + count <= HR_COUNT):
        raise DeviceError(ILLEGAL_ADDRESS, f"holding registers {address}..{address + count - 1}")


def _holding_value_ok(reg: int, value: int) -> bool:
    if reg == HR_SCAN_RATE:
        return SCAN_RATE_MIN_HZ <= value <= SCAN_RATE_MAX_HZ
    if reg == HR_OVERSAMPLING:
        return value in OVERSAMPLING_CHOICES
    return value in (0, 1)
