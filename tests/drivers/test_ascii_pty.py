"""The ASCII driver against a scripted odd device on a real pseudo-terminal.

The emulator behaves like the datasheet; a real module may not. Here a small responder
thread sits on the master side of a pty and answers each command with whatever a test
scripts (wrong model, partial frames, split frames, junk lines, silence), while the driver
opens the slave side with pyserial exactly as it would open /dev/ttyUSB0.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator

import pytest

from loopcal.drivers import ldq412, open_daq
from loopcal.drivers.errors import DAQIdentityError, DAQInvalidCommand, DAQProtocolError, DAQTimeout
from tests.support.drivers import worst_call_s

Reply = bytes | list[tuple[float, bytes]] | None
Handler = Callable[[bytes], Reply]

SCAN = b">0000123400ABCDEF800001FFFBB80004"


class ScriptedDevice:
    """Answers each CR-terminated command with handler(command without CR).

    A reply is bytes (written at once), a list of (delay_s, bytes) pieces, or None.
    """

    def __init__(self, handler: Handler) -> None:
        self.handler = handler
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        self._slave = slave  # keep open so the master never sees EIO between opens
        self._stop = threading.Event()
        self.commands: list[bytes] = []
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            r, _, _ = select.select([self.master], [], [], 0.02)
            if not r:
                continue
            try:
                buf += os.read(self.master, 4096)
            except OSError:
                return
            while b"\r" in buf:
                cmd, buf = buf.split(b"\r", 1)
                self.commands.append(cmd)
                reply = self.handler(cmd)
                if reply is None:
                    continue
                pieces = [(0.0, reply)] if isinstance(reply, bytes) else reply
                for delay, data in pieces:
                    time.sleep(delay)
                    os.write(self.master, data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1)
        os.close(self.master)
        os.close(self._slave)


def good_device(cmd: bytes) -> Reply:
    return {
        b"$01M": b"!01LDQ412\r",
        b"$01F": b"!012.01\r",
        b"$01R": b"!010014\r",
        b"#01": SCAN + b"\r",
    }.get(cmd, b"?01\r")


@pytest.fixture
def device() -> Iterator[Callable[[Handler], ScriptedDevice]]:
    made: list[ScriptedDevice] = []

    def make(handler: Handler) -> ScriptedDevice:
        d = ScriptedDevice(handler)
        made.append(d)
        return d

    yield make
    for d in made:
        d.close()


def url(dev: ScriptedDevice, extra: str = "") -> str:
    return f"ascii://{dev.path}?baud=115200&addr=01{extra}"


#: s, the driver's timeout where the device answers: the responder is a thread of this
#: process, which a loaded machine can hold past the datasheet's 0.1 s (it did, at connect,
#: in a whole run on four workers); a test that bounds a timeout sets the datasheet's
ANSWERED_S = 1.0


def connect(dev: ScriptedDevice, extra: str = "", **options):
    """The driver on the device, its timeout :data:`ANSWERED_S`."""
    return open_daq(url(dev, extra), timeout=ANSWERED_S, **options)


def test_identity_at_connect(device) -> None:
    dev = device(good_device)
    with connect(dev) as daq:
        assert daq.identity.model == ldq412.MODEL_NAME
        assert daq.identity.firmware == "2.01"
        assert daq.identity.serial is None  # the ASCII protocol has no serial query
        assert daq.read_scan_rate() == 20
        scans = daq.read_scans()
        assert [s.counter for s in scans] == [0x1234]
        assert scans[0].codes == (2048, 1, 4095, 3000) and scans[0].rail[2]
        assert daq.read_scans() == []  # same counter again: deduplicated


def test_wrong_model_is_an_identity_error(device) -> None:
    dev = device(lambda c: b"!01LDQ999\r" if c == b"$01M" else good_device(c))
    with pytest.raises(DAQIdentityError):
        connect(dev)
    with connect(dev, check_identity=False) as daq:
        assert daq.identity.model == "LDQ999"


def test_a_late_answer_to_an_earlier_request_is_not_taken_for_the_model(device) -> None:
    """ci53: a connect given up on had its "$01F" answered late, and the next connect's
    "$01M" read that answer, "!013.07", as the model: DAQIdentityError for an LDQ-412. Both
    are "!01..." answers. Here the late answer comes just before the model's, every time
    the first "$01M" is asked; the driver asks again on a quiet line."""
    asked = []

    def late_firmware_first(cmd: bytes) -> Reply:
        if cmd == b"$01M" and not asked:
            asked.append(cmd)
            return [(0.0, b"!013.07\r"), (0.0, b"!01LDQ412\r")]  # an earlier request's first
        return good_device(cmd)

    dev = device(late_firmware_first)
    with connect(dev) as daq:
        assert daq.identity.model == ldq412.MODEL_NAME and daq.identity.firmware == "2.01"
    assert dev.commands.count(b"$01M") == 2


def test_silent_device_times_out_within_the_bound(device) -> None:
    dev = device(good_device)
    daq = connect(dev)
    dev.handler = lambda c: None
    daq.timeout = ldq412.HOST_TIMEOUT_S  # the datasheet's, which this bounds
    t0 = time.monotonic()
    with pytest.raises(DAQTimeout):
        daq.read_scans()
    assert time.monotonic() - t0 < worst_call_s(ldq412.HOST_TIMEOUT_S)
    daq.timeout = ANSWERED_S
    dev.handler = good_device
    assert [s.counter for s in daq.read_scans()] == [0x1234]
    daq.close()


@pytest.mark.parametrize(
    ("reply", "error"),
    [
        (SCAN, DAQProtocolError),  # partial: no CR ever
        (SCAN[:20] + b"\r", DAQProtocolError),  # truncated
        (b"\x13\x88junk\r" + SCAN + b"\r", DAQProtocolError),  # junk line first
        (b"zz" + SCAN + b"\r", DAQProtocolError),  # junk glued to the answer
        (SCAN.replace(b"8000", b"8g00") + b"\r", DAQProtocolError),  # non-hex
        (b"?01\r", DAQInvalidCommand),
        (b"!01\r", DAQProtocolError),  # an ack where a scan was expected
        (b"A" * 500, DAQProtocolError),  # babbling, no CR
    ],
)
def test_malformed_answers_then_recovery(device, reply: bytes, error: type) -> None:
    dev = device(good_device)
    daq = connect(dev)
    dev.handler = lambda c: reply if c == b"#01" else good_device(c)
    t0 = time.monotonic()
    with pytest.raises(error):
        daq.read_scans()
    assert time.monotonic() - t0 < worst_call_s(ANSWERED_S)  # a babbling device ends too
    dev.handler = good_device
    assert [s.counter for s in daq.read_scans()] == [0x1234]
    daq.close()


def test_split_and_lowercase_answers_are_accepted(device) -> None:
    lower = SCAN.lower().replace(b"g", b"G")
    dev = device(
        lambda c: (
            [(0.0, lower[:10]), (0.01, lower[10:]), (0.01, b"\r")]
            if c == b"#01"
            else good_device(c)
        )
    )
    with connect(dev) as daq:
        (s,) = daq.read_scans()
        assert s.time_us == 0xABCDEF


def test_checksum_mode(device) -> None:
    def with_cs(cmd: bytes) -> Reply:
        body, digits = cmd[:-2], cmd[-2:]
        if digits != ldq412.ascii_checksum(body):
            return None
        plain = good_device(body)
        assert isinstance(plain, bytes)
        ans = plain[:-1]
        return ans + ldq412.ascii_checksum(ans) + b"\r"

    dev = device(with_cs)
    with connect(dev, "&checksum=1") as daq:
        assert [s.counter for s in daq.read_scans()] == [0x1234]
        assert dev.commands[-1] == b"#0184"
        bad = SCAN + b"00\r"
        dev.handler = lambda c: bad
        with pytest.raises(DAQProtocolError, match="checksum"):
            daq.read_scans()
    # a module in checksum mode ignores commands without digits: the error says what
    # to check
    dev.handler = with_cs
    with pytest.raises(DAQTimeout, match="checksum"):
        open_daq(url(dev, "&checksum=0"))
