"""The LDQ-412 ASCII protocol (datasheet "ASCII protocol"), as pure functions.

:func:`handle_frame` takes one received frame (the bytes before a CR) and returns the
complete answer (CR included) or None for no answer at all.

Decisions where the datasheet is silent:

- A frame is addressed to this module when it is printable ASCII, its first byte is not
  one of the answer characters ``>``, ``!``, ``?`` (so answers of other modules on a shared
  line are never taken for commands) and bytes 1..2 are the address as two uppercase hex
  digits. Anything else gets no answer (line noise, other modules, lowercase address).
- With checksum mode on, a frame shorter than its two checksum digits, or whose checksum
  digits are not the exact uppercase hex of the sum, gets no answer.
- The scan-rate digits of ``%AARhhhh`` are exactly four hex digits, either case; a rate
  outside 1..200 Hz answers ``?AA`` (like any invalid command) and changes nothing.
"""

from __future__ import annotations

import string

from loopcal.drivers.ldq412 import MODEL_NAME, ascii_checksum

from .device import LDQ412
from .registers import DeviceError

CR = b"\r"
_PRINTABLE = frozenset(string.printable.encode()) - frozenset(b"\t\n\r\x0b\x0c")
_ANSWER_LEADS = frozenset(b">!?")
_HEX = frozenset(b"0123456789ABCDEFabcdef")


def encode_answer(body: bytes, checksum: bool) -> bytes:
    """Frame an answer: ``body`` + (checksum digits) + CR.

    Parameters
    ----------
    body : bytes
        The answer without framing, e.g. ``b"!01LDQ412"``.
    checksum : bool
        The checksum mode: add two uppercase hex digits, the sum of ``body``'s bytes
        modulo 256.

    Returns
    -------
    bytes
        The complete answer, CR included.
    """
    return body + (ascii_checksum(body) if checksum else b"") + CR


def latest_scan_body(device: LDQ412) -> bytes:
    """The ``#AA`` answer without framing: ``>`` counter time ch1..ch4 status.

    Parameters
    ----------
    device : LDQ412
        The module, ready and synced; reading its latest scan counts as a host's read.

    Returns
    -------
    bytes
        ``>`` then the counter (8 hex digits), the device time in µs (8), channel 1..4
        codes (3 each) and the status register (4), uppercase.

    Raises
    ------
    DeviceOffError
        If the module is not ready.
    """
    s = device.latest
    text = f">{s.counter:08X}{s.time_us:08X}" + "".join(f"{c:03X}" for c in s.codes)
    return (text + f"{device.status:04X}").encode()


def handle_frame(device: LDQ412, frame: bytes, address: int) -> bytes | None:
    """Answer one received frame (without its CR), or None for no answer.

    Parameters
    ----------
    device : LDQ412
        The module, ready and synced (a ``%AARhhhh`` sets its scan rate).
    frame : bytes
        The bytes received before a CR.
    address : int
        The module address, 0..255.

    Returns
    -------
    bytes or None
        The complete answer (checksum digits and CR included), or None: no answer at all
        (not printable, not addressed to this module, a wrong or missing checksum, or an
        answer lead ``>``, ``!``, ``?``). A command it does not know, for this address,
        answers ``?AA``.

    Raises
    ------
    DeviceOffError
        If the module is not ready when the command reads it.
    """
    if not frame or any(b not in _PRINTABLE for b in frame):
        return None
    checksum = device.ascii_checksum
    if checksum:
        if len(frame) < 2:
            return None
        body, digits = frame[:-2], frame[-2:]
        if digits != ascii_checksum(body):
            return None
    else:
        body = frame
    aa = b"%02X" % address
    if len(body) < 3 or body[0] in _ANSWER_LEADS or body[1:3] != aa:
        return None
    answer = _dispatch(device, body[0:1], body[3:], aa)
    return encode_answer(answer, checksum)


def _dispatch(device: LDQ412, lead: bytes, rest: bytes, aa: bytes) -> bytes:
    invalid = b"?" + aa
    if lead == b"#":
        if rest == b"":
            return latest_scan_body(device)
        if rest in (b"1", b"2", b"3", b"4"):
            return b">%03X" % device.latest.codes[int(rest) - 1]
        return invalid
    if lead == b"$":
        if rest == b"M":
            return b"!" + aa + MODEL_NAME.encode()
        if rest == b"F":
            return b"!" + aa + device.firmware_text.encode()
        if rest == b"R":
            return b"!" + aa + b"%04X" % device.scan_rate_hz
        return invalid
    if lead == b"%":
        if len(rest) == 5 and rest[:1] == b"R" and all(b in _HEX for b in rest[1:]):
            try:
                device.set_scan_rate(int(rest[1:], 16))
            except DeviceError:
                return invalid
            return b"!" + aa
        return invalid
    return invalid
