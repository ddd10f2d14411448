"""Driver URLs: :func:`parse_url` splits one into a :class:`DaqUrl` (scheme, endpoint, query
parameters), whose getters check each value; :func:`serial_options` reads a serial line's.

A URL names a module and how to reach it, as pyserial's ``serial_for_url`` and python-can's
interfaces do::

    modbus-tcp://host:port?unit=1[&fifo=1]
    modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1[&parity=N&stopbits=1&fifo=1]
    ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=1
    modbus-rtu://host:port?unit=1[&baud=115200&parity=N&stopbits=1&fifo=1]
    ascii://host:port?addr=01&checksum=1[&baud=115200]

The last two reach the serial line through a serial device server in raw TCP mode (a Moxa
NPort's "TCP server" mode): its TCP port carries the line's bytes unchanged. The drivers
open it as pyserial's ``socket://host:port`` (:func:`socket_line`; :func:`device_server`
reads one back, :func:`line_url` writes one as a URL again); the line's rate, parity and
stop bits are then the device server's settings, which pyserial ignores on a socket.

Nothing here knows the drivers: :mod:`loopcal.drivers.registry` picks one by the scheme.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from urllib.parse import parse_qsl, urlsplit

from . import ldq412


@dataclass(frozen=True, slots=True)
class DaqUrl:
    """A parsed driver URL (:func:`parse_url`).

    Attributes
    ----------
    scheme : str
        The scheme in lower case, e.g. ``"modbus-tcp"``.
    host : str or None
        Network host, lower case, without an IPv6 address's brackets (None for a serial
        device's URL, ``ascii:///dev/ttyUSB0``).
    port : int or None
        Network port, or None if the URL gives none.
    path : str
        Serial device: the URL's path (``"/dev/ttyUSB0"`` in ``ascii:///dev/ttyUSB0``),
        or its netloc if it has no path and no port (``"COM3"`` in ``ascii://COM3``);
        ``""`` for a URL with a host and a port and no path (a network URL, or a serial
        device server's, ``ascii://192.168.1.60:4001``).
    params : Mapping[str, str]
        Query parameters, every value a string as written (read-only).
    raw : str
        The URL as given (for error messages).
    """

    scheme: str
    host: str | None
    port: int | None
    path: str
    params: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}))
    raw: str = ""

    def get_int(
        self, key: str, default: int, *, base: int = 10, lo: int | None = None,
        hi: int | None = None,
    ) -> int:  # fmt: skip
        """An integer query parameter.

        Parameters
        ----------
        key : str
            The parameter's name.
        default : int
            What an absent parameter gives (not checked against ``lo..hi``).
        base : int
            10 (an optional ``-`` and 1-20 digits) or 16 (1-16 hex digits, no ``0x``).
        lo, hi : int or None
            Inclusive bounds, None for none.

        Returns
        -------
        int
            The value, or ``default``.

        Raises
        ------
        ValueError
            If the value is not such a number (``int()``'s leniency, `` 1``, ``1_0``,
            ``+1``, is refused) or outside ``lo..hi``; the message names the URL, the
            parameter and the value.
        """
        value = self.params.get(key)
        if value is None:
            return default
        digits = _HEX_RE if base == 16 else _INT_RE
        if not digits.match(value):  # int() would also take " 1", "1_0" and "+1"
            kind = "a hexadecimal number" if base == 16 else "an integer"
            raise ValueError(f"{self.raw}: {key}={value!r} is not {kind}")
        out = int(value, base)
        if (lo is not None and out < lo) or (hi is not None and out > hi):
            raise ValueError(f"{self.raw}: {key}={value} is outside {lo}..{hi}")
        return out

    def get_choice(self, key: str, default: str, choices: tuple[str, ...]) -> str:
        """A query parameter that must be one of ``choices``, compared in upper case.

        Parameters
        ----------
        key : str
            The parameter's name.
        default : str
            What an absent parameter gives.
        choices : tuple of str
            The allowed values, in upper case (e.g. ``("N", "E", "O")``).

        Returns
        -------
        str
            The value in upper case, or ``default``.

        Raises
        ------
        ValueError
            If the value is not one of ``choices``, naming the URL and the choices.
        """
        value = self.params.get(key)
        if value is None:
            return default
        if value.upper() not in choices:
            raise ValueError(f"{self.raw}: {key}={value!r} is not one of {', '.join(choices)}")
        return value.upper()

    def get_bool(self, key: str, default: bool) -> bool:
        """A boolean query parameter: 0/1, also false/true, no/yes, off/on.

        Parameters
        ----------
        key : str
            The parameter's name.
        default : bool
            What an absent parameter gives.

        Returns
        -------
        bool
            The value, or ``default``.

        Raises
        ------
        ValueError
            If the value is none of those words, naming the URL and the parameter.
        """
        value = self.params.get(key)
        if value is None:
            return default
        v = value.strip().lower()
        if v in ("1", "true", "yes", "on"):
            return True
        if v in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"{self.raw}: {key}={value!r} is not a boolean (0/1)")


_SCHEME_RE = re.compile(r"^[a-z][a-z0-9+.-]*$")
_INT_RE = re.compile(r"^-?[0-9]{1,20}\Z")
_HEX_RE = re.compile(r"^[0-9A-Fa-f]{1,16}\Z")


def parse_url(url: str) -> DaqUrl:
    """Split a driver URL into scheme, endpoint and query parameters, without checking
    them against a driver (:func:`driver_for_url` does).

    Parameters
    ----------
    url : str
        ``scheme://host[:port][?query]`` or ``scheme:///device[?query]``, e.g.
        ``"modbus-tcp://192.168.1.50:502?unit=1"``, ``"ascii:///dev/ttyUSB0?addr=01"``.

    Returns
    -------
    DaqUrl
        The parts.

    Raises
    ------
    ValueError
        On control characters, a missing or malformed scheme (or no ``://``), a query
        parameter given twice, or a malformed port.
    """
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in url):
        raise ValueError(f"{url!r}: control characters in a DAQ URL")
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if not scheme or not _SCHEME_RE.match(scheme) or "://" not in url:
        raise ValueError(f"not a DAQ URL (scheme://...): {url!r}")
    params: dict[str, str] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True, strict_parsing=False):
        if key in params:
            raise ValueError(f"{url}: query parameter {key!r} given twice")
        params[key] = value
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"{url}: malformed port") from None
    host = parts.hostname
    # Serial URLs carry the device in the path ("ascii:///dev/ttyUSB0") or, for Windows
    # names, in the netloc ("ascii://COM3").
    if parts.path and parts.path != "/":
        path = parts.path if not parts.netloc else parts.netloc + parts.path
    else:
        path = parts.netloc if parts.netloc and port is None else ""
    return DaqUrl(scheme, host, port, path, MappingProxyType(params), url)


#: the fastest serial line a URL may ask for (RS-485 transceivers top out around here)
MAX_BAUD = 4_000_000


#: the scheme of pyserial's URL of a raw TCP line (a serial device server's port)
SOCKET_SCHEME = "socket"


def host_port(host: str, port: int) -> str:
    """``HOST:PORT`` as a URL writes it (an IPv6 address in brackets).

    Parameters
    ----------
    host : str
        Host name or address, without brackets.
    port : int
        TCP port.

    Returns
    -------
    str
        E.g. ``"192.168.1.60:4001"``, ``"[fe80::1]:4001"``.
    """
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def socket_line(host: str, port: int) -> str:
    """The serial line behind a serial device server's TCP port, as pyserial opens it.

    Parameters
    ----------
    host : str
        The device server's host name or address (an IPv6 address without brackets).
    port : int
        Its TCP port that carries the line's bytes (raw TCP server mode).

    Returns
    -------
    str
        ``"socket://HOST:PORT"`` (pyserial's ``serial_for_url`` opens it).
    """
    return f"{SOCKET_SCHEME}://{host_port(host, port)}"


def device_server(line: str) -> tuple[str, int] | None:
    """The serial device server a serial line is reached through, if it is one.

    Parameters
    ----------
    line : str
        A serial driver's ``port``: a device (``"/dev/ttyUSB0"``) or a pyserial URL.

    Returns
    -------
    tuple of (str, int) or None
        ``(host, port)`` (the host in lower case, without brackets) for
        ``"socket://HOST:PORT"`` (:func:`socket_line`); None for anything else, a device
        or another pyserial URL.
    """
    if not line.startswith(f"{SOCKET_SCHEME}://"):  # pyserial's own test: lower case only
        return None
    parts = urlsplit(line)
    try:
        port = parts.port
    except ValueError:
        return None
    if not parts.hostname or port is None:
        return None
    return parts.hostname, port


def line_url(scheme: str, line: str) -> str:
    """A serial line written as a URL of a driver's scheme, without the query: what
    :func:`parse_url` and :func:`serial_options` read back as the same line.

    Parameters
    ----------
    scheme : str
        The driver's scheme, e.g. ``"ascii"``.
    line : str
        The driver's ``port``: a device, or ``"socket://HOST:PORT"``.

    Returns
    -------
    str
        ``"SCHEME://HOST:PORT"`` for a device server's line (:func:`device_server`),
        ``"SCHEME://DEVICE"`` (``"ascii:///dev/ttyUSB0"``) for anything else.
    """
    server = device_server(line)
    return f"{scheme}://{host_port(*server) if server else line}"


def serial_options(url: DaqUrl, example: str) -> dict[str, object]:
    """The serial line a URL names, every value checked (for the serial drivers'
    :meth:`DAQ.url_options`).

    Parameters
    ----------
    url : DaqUrl
        A parsed serial URL: a device in its path (``ascii:///dev/ttyUSB0``, or
        ``ascii://COM3``), or a serial device server's host and TCP port
        (``ascii://192.168.1.60:4001``, no path).
    example : str
        A URL of the scheme with a device, quoted in the error if the URL names no line.

    Returns
    -------
    dict
        ``port``: the line as ``serial.serial_for_url`` opens it, the URL's path (a
        device) or, for a host and port, ``"socket://HOST:PORT"`` (:func:`socket_line`);
        ``baud`` (1..:data:`MAX_BAUD`, default 115200), ``parity`` (``"N"``, ``"E"`` or
        ``"O"``, default ``"N"``) and ``stopbits`` (1 or 2, default 1): the datasheet's
        115200 8N1 unless the URL says otherwise. On a device server's line these three
        are checked alike but only say what its serial side is set to: pyserial ignores
        them on a socket.

    Raises
    ------
    ValueError
        If the URL names neither a device nor a host and a TCP port (1..65535), or a value
        is out of range, naming the URL.
    """
    if url.path:
        line = url.path
    elif url.host and url.port:
        line = socket_line(url.host, url.port)
    elif url.host and url.port == 0:
        raise ValueError(f"{url.raw}: port 0 is not a TCP port")
    else:
        raise ValueError(
            f"{url.raw}: no serial port ({example}, or {url.scheme}://HOST:PORT for a "
            "serial device server's TCP port)"
        )
    return {
        "port": line,
        "baud": url.get_int("baud", ldq412.SERIAL_BAUD, lo=1, hi=MAX_BAUD),
        "parity": url.get_choice("parity", "N", ("N", "E", "O")),
        "stopbits": url.get_int("stopbits", 1, lo=1, hi=2),
    }
