"""The Modbus TCP driver against a scripted odd device on a real TCP socket.

The emulator is a well-behaved LDQ-412; this is a device that is not: wrong model code,
answers of the wrong length, out-of-range values. Frames are built and decoded with
pymodbus' own framer (nothing hand-framed); a test scripts the register contents.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterator

import pytest
from pymodbus.framer import FramerSocket
from pymodbus.pdu import ModbusPDU
from pymodbus.pdu.decoders import DecodePDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersResponse,
    ReadInputRegistersResponse,
    WriteSingleRegisterResponse,
)

from loopcal.drivers import ldq412, open_daq
from loopcal.drivers.errors import DAQIdentityError, DAQProtocolError

Regs = Callable[[int, int], list[int]]


def good_input(address: int, count: int) -> list[int]:
    if address == ldq412.IR_MODEL:
        return [ldq412.MODEL_CODE, 0x0201, 0, 7]
    if address == 0:
        return [0, 10, 0x7, 0xA120, 1, 2, 3, 4, 0, 0]
    return [0xFFFF] * count


class ScriptedModbusTcp:
    """One-connection-at-a-time Modbus TCP device answering from ``self.input``."""

    def __init__(self, input_regs: Regs) -> None:
        self.input = input_regs
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self._stop = False
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        self.sock.settimeout(0.05)
        while not self._stop:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            with conn:
                self._session(conn)

    def _session(self, conn: socket.socket) -> None:
        framer = FramerSocket(DecodePDU(True))
        conn.settimeout(0.05)
        buf = b""
        while not self._stop:
            try:
                data = conn.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            if not data:
                return
            buf += data
            used, req = framer.handleFrame(buf, 0, 0)
            buf = buf[used:]
            if req is None:
                continue
            rsp = self._answer(req)
            rsp.transaction_id, rsp.dev_id = req.transaction_id, req.dev_id
            conn.sendall(framer.buildFrame(rsp))

    def _answer(self, req: ModbusPDU) -> ModbusPDU:
        if req.function_code == 4:
            return ReadInputRegistersResponse(registers=self.input(req.address, req.count))
        if req.function_code == 3:
            return ReadHoldingRegistersResponse(registers=[20] * req.count)
        return WriteSingleRegisterResponse(address=req.address, registers=req.registers)

    @property
    def url(self) -> str:
        return f"modbus-tcp://127.0.0.1:{self.port}?unit=1"

    def close(self) -> None:
        self._stop = True
        self._thread.join(1)
        self.sock.close()


@pytest.fixture
def device() -> Iterator[Callable[[Regs], ScriptedModbusTcp]]:
    made: list[ScriptedModbusTcp] = []

    def make(regs: Regs) -> ScriptedModbusTcp:
        made.append(ScriptedModbusTcp(regs))
        return made[-1]

    yield make
    for d in made:
        d.close()


def test_scripted_device_works(device) -> None:
    dev = device(good_input)
    with open_daq(dev.url) as daq:
        assert daq.identity.serial == 7
        (s,) = daq.read_scans() or [daq.snapshot()]
        assert s.counter == 10 and s.codes == (1, 2, 3, 4)


def test_wrong_model_code(device) -> None:
    dev = device(lambda a, c: [0x0999, 0x0201, 0, 7] if a == ldq412.IR_MODEL else good_input(a, c))
    with pytest.raises(DAQIdentityError):
        open_daq(dev.url)
    with open_daq(dev.url, check_identity=False) as daq:
        assert daq.identity.model_code == 0x0999


@pytest.mark.parametrize(
    "snapshot",
    [
        [0, 10, 0x7, 0xA120, 1, 2, 3, 4, 0],  # one register short
        [0, 10, 0x7, 0xA120, 1, 2, 3, 4, 0, 0, 0],  # one too many
        [0, 10, 0x7, 0xA120, 1, 4096, 3, 4, 0, 0],  # code out of range
        [0, 10, 0x7, 0xA120, 1, 2, 3, 4, 0, 300],  # FIFO level > 256
    ],
)
def test_malformed_snapshot_is_a_protocol_error(device, snapshot: list[int]) -> None:
    state = {"bad": False}
    dev = device(lambda a, c: snapshot if a == 0 and state["bad"] else good_input(a, c))
    with open_daq(dev.url) as daq:
        state["bad"] = True
        with pytest.raises(DAQProtocolError):
            daq.read_scans()
        state["bad"] = False
        assert daq.snapshot().counter == 10


def test_fifo_partial_filler_is_a_protocol_error_and_the_driver_continues(device) -> None:
    calls = {"n": 0}

    def regs(a: int, c: int) -> list[int]:
        if a == 0:
            return [0, 12, 0x9, 0x27C0, 1, 2, 3, 4, 0, 2 if calls["n"] == 0 else 0]
        if a == ldq412.IR_FIFO:
            calls["n"] += 1
            if calls["n"] == 1:  # first read: asks for 2 (and 1 more), gets a broken second
                return [0, 11, 5, 6, 7, 8, 0, 12, 0xFFFF, 0xFFFF, 0xFFFF, 0xFFFF]
        return good_input(a, c)

    dev = device(regs)
    with open_daq(dev.url) as daq:
        with pytest.raises(DAQProtocolError):
            daq.read_scans()
        assert daq.read_scans() == []  # nothing was parsed from the broken answer
