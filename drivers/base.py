"""Abstract DAQ interface and URL -> driver dispatch (the records a driver returns,
:class:`Scan` and :class:`Identity`, are :mod:`loopcal.drivers.records`'s, exported here too).

A driver is chosen by the scheme of a URL, as pyserial's ``serial_for_url`` and
python-can's interfaces do::

    modbus-tcp://host:port?unit=1[&fifo=1]
    modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1[&parity=N&stopbits=1&fifo=1]
    ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=1

Drivers register their scheme with :func:`register_scheme`; :func:`open_daq` parses the
URL, rejects unknown query parameters, and hands the parsed URL to the driver class.

A driver gives its scans two ways, as python-can's buses give messages: :meth:`DAQ.read_scans`
returns at once what arrived since the previous call, and :meth:`DAQ.scans` (``for scan in
daq``) is a stream that reads at the module's own pace (:mod:`loopcal.drivers.pacing`),
for a duration or until no scan comes within a timeout::

    with open_daq("ascii:///dev/ttyUSB0?addr=01") as daq:
        for scan in daq.scans(timeout=1.0, duration=60.0):
            print(scan.counter64, scan.volts)
"""

from __future__ import annotations

import importlib
import math
import numbers
import re
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import ClassVar, TypeVar
from urllib.parse import parse_qsl, urlsplit

from . import ldq412
from .errors import DAQError, DAQTimeout
from .pacing import FifoPacer, PollPacer
from .records import Identity, Scan
from .sequence import Sequencer


@dataclass(frozen=True, slots=True)
class DaqUrl:
    """A parsed driver URL (:func:`parse_url`).

    Attributes
    ----------
    scheme : str
        The scheme in lower case, e.g. ``"modbus-tcp"``.
    host : str or None
        Network host, lower case (None for serial URLs, ``ascii:///dev/ttyUSB0``).
    port : int or None
        Network port, or None if the URL gives none.
    path : str
        Serial device: the URL's path (``"/dev/ttyUSB0"`` in ``ascii:///dev/ttyUSB0``),
        or its netloc if it has no path and no port (``"COM3"`` in ``ascii://COM3``);
        ``""`` for a network URL with a port.
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


def serial_options(url: DaqUrl, example: str) -> dict[str, object]:
    """The serial line a URL names, every value checked (for the serial drivers'
    :meth:`DAQ.url_options`).

    Parameters
    ----------
    url : DaqUrl
        A parsed serial URL.
    example : str
        A URL of the scheme with a port, quoted in the error if the URL has none.

    Returns
    -------
    dict
        ``port`` (the URL's path), ``baud`` (1..:data:`MAX_BAUD`, default 115200),
        ``parity`` (``"N"``, ``"E"`` or ``"O"``, default ``"N"``) and ``stopbits`` (1 or
        2, default 1): the datasheet's 115200 8N1 unless the URL says otherwise.

    Raises
    ------
    ValueError
        If the URL names no port or a value is out of range, naming the URL.
    """
    if not url.path:
        raise ValueError(f"{url.raw}: no serial port ({example})")
    return {
        "port": url.path,
        "baud": url.get_int("baud", ldq412.SERIAL_BAUD, lo=1, hi=MAX_BAUD),
        "parity": url.get_choice("parity", "N", ("N", "E", "O")),
        "stopbits": url.get_int("stopbits", 1, lo=1, hi=2),
    }


#: s between two tries of a stream (DAQ.scans) after a failed read, as the daemon's retries
#: through a power cycle's restart window
STREAM_RETRY_S = 0.05


def _seconds(name: str, value: float | None) -> float | None:
    """A stream's timeout or duration, checked: None, or a finite number of s > 0."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a number of seconds or None, got {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number of seconds > 0 (or None), got {value}")
    return float(value)


def _sleep_until(t: float) -> None:
    """Sleep until host monotonic time ``t`` (s); return at once if it has passed."""
    wait = t - time.monotonic()
    if wait > 0:
        time.sleep(wait)


D = TypeVar("D", bound="DAQ")
_REGISTRY: dict[str, type[DAQ]] = {}


def register_scheme(scheme: str) -> Callable[[type[D]], type[D]]:
    """Class decorator: make :func:`open_daq` open URLs of ``scheme`` with the class.

    Parameters
    ----------
    scheme : str
        The URL scheme, lower case (e.g. ``"modbus-tcp"``); set as the class's
        :attr:`DAQ.scheme`.

    Returns
    -------
    Callable[[type[DAQ]], type[DAQ]]
        The decorator; it returns the class unchanged.

    Raises
    ------
    ValueError
        When the decorator is applied, if another class has registered ``scheme``.
    """

    def deco(cls: type[D]) -> type[D]:
        if scheme in _REGISTRY and _REGISTRY[scheme] is not cls:
            raise ValueError(f"URL scheme {scheme!r} already registered")
        _REGISTRY[scheme] = cls
        cls.scheme = scheme
        return cls

    return deco


#: the modules of the drivers that come with loopcal; each registers its scheme on import
_BUILTIN = ("loopcal.drivers.modbus_tcp", "loopcal.drivers.modbus_rtu", "loopcal.drivers.ascii")


def _load_builtin() -> None:
    """Import the built-in drivers (on first need: they bring pymodbus and pyserial)."""
    for module in _BUILTIN:
        importlib.import_module(module)


def registered_schemes() -> dict[str, type[DAQ]]:
    """The registered drivers, the built-in ones imported first.

    Returns
    -------
    dict[str, type[DAQ]]
        Scheme -> driver class (a copy).
    """
    _load_builtin()
    return dict(_REGISTRY)


def driver_for_url(url: str) -> tuple[type[DAQ], DaqUrl]:
    """The driver class a URL names and the parsed URL, every value checked, without
    connecting.

    Parameters
    ----------
    url : str
        A driver URL (see :func:`parse_url` and the drivers' docstrings).

    Returns
    -------
    tuple[type[DAQ], DaqUrl]
        The driver class registered for the URL's scheme, and the parsed URL.

    Raises
    ------
    ValueError
        For a malformed URL, an unknown scheme (naming the known ones), a query parameter
        the driver does not take (naming those it takes), or a value out of range.
    """
    parsed = parse_url(url)
    if parsed.scheme not in _REGISTRY:
        _load_builtin()
    try:
        cls = _REGISTRY[parsed.scheme]
    except KeyError:
        known = ", ".join(sorted(_REGISTRY))
        raise ValueError(f"unknown DAQ URL scheme {parsed.scheme!r} (known: {known})") from None
    unknown = set(parsed.params) - set(cls.url_params)
    if unknown:
        raise ValueError(
            f"{url}: unknown parameter(s) {sorted(unknown)} for {parsed.scheme} "
            f"(allowed: {sorted(cls.url_params)})"
        )
    cls.url_options(parsed)  # every value checked now, not when the driver connects
    return cls, parsed


def open_daq(
    url: str, *, timeout: float = ldq412.HOST_TIMEOUT_S, check_identity: bool = True
) -> DAQ:
    """Open the driver the URL's scheme names and connect to the module.

    Parameters
    ----------
    url : str
        ``modbus-tcp://host[:port]?unit=1[&fifo=1]``,
        ``modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1[&parity=N&stopbits=1&fifo=1]`` or
        ``ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=0``.
    timeout : float
        s without an answer before a call raises DAQTimeout (> 0; datasheet: 0.1 s).
    check_identity : bool
        Raise DAQIdentityError unless the module identifies as an LDQ-412.

    Returns
    -------
    DAQ
        The connected driver (a context manager: ``with open_daq(url) as daq: ...``).

    Raises
    ------
    ValueError
        For a malformed URL, an unknown scheme, an unknown or bad query parameter, or a
        timeout that is not > 0.
    DAQError
        The driver's subclasses: DAQDisconnected (cannot connect), DAQTimeout (no answer
        at connect), DAQProtocolError, DAQIdentityError (not an LDQ-412).
    """
    cls, parsed = driver_for_url(url)
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0 s, got {timeout}")
    return cls.from_url(parsed, timeout=timeout, check_identity=check_identity)


class DAQ(ABC):
    """An LDQ-412 module reached over one transport; :func:`open_daq` opens one by URL.

    Every call is bounded in time by the timeout given at open (plus the transfer time
    of the answer) and either returns valid data or raises a DAQError; after an error
    the next call tries again (reconnecting if needed). A DAQ is not thread-safe: one
    thread (or one lock) per instance. Scans come by :meth:`read_scans` (what arrived
    since the previous call, at once) or by the stream :meth:`scans` (``for scan in
    daq``); a DAQ is a context manager that closes it.

    A driver subclass registers its scheme (:func:`register_scheme`), lists its
    :attr:`url_params`, turns a URL into its constructor's arguments
    (:meth:`url_options`), sets :attr:`identity`, :attr:`url` and the sequencer at
    connect, and implements :meth:`read_scans`, :meth:`snapshot`, :meth:`clear_restart`,
    :meth:`close` and the scan rate's getter and setter.

    Attributes
    ----------
    scheme : str
        The URL scheme the class is registered for (class attribute).
    url_params : frozenset of str
        The query parameters its URLs may carry (class attribute).
    identity : Identity
        What the module said it is at connect.
    url : str
        The URL of the connection, every parameter written out.
    """

    scheme: ClassVar[str] = ""
    # query parameters accepted in the URL
    url_params: ClassVar[frozenset[str]] = frozenset()

    identity: Identity
    url: str
    #: links the driver's successive reads into one scan sequence; set at connect
    _seq: Sequencer
    #: scans taken off the module and not yet returned: the next read_scans returns them first
    _pending: list[Scan]
    #: True once close() was called (every call then raises DAQDisconnected)
    _closed: bool

    @classmethod
    def url_options(cls, url: DaqUrl) -> dict[str, object]:
        """The constructor's keyword arguments a parsed URL gives, every value checked,
        without connecting.

        Parameters
        ----------
        url : DaqUrl
            A URL of the class's scheme, its parameters among :attr:`url_params`.

        Returns
        -------
        dict[str, object]
            Keyword arguments for the constructor (without ``timeout`` and
            ``check_identity``).

        Raises
        ------
        ValueError
            Naming the URL, the parameter and the value.
        """
        return {}

    @classmethod
    def from_url(cls, url: DaqUrl, *, timeout: float, check_identity: bool) -> DAQ:
        """Connect to the module a parsed URL describes (what :func:`open_daq` calls).

        Parameters
        ----------
        url : DaqUrl
            A URL of the class's scheme.
        timeout : float
            s without an answer before a call raises DAQTimeout.
        check_identity : bool
            Raise DAQIdentityError unless the module identifies as an LDQ-412.

        Returns
        -------
        DAQ
            The connected driver.

        Raises
        ------
        ValueError
            For a bad URL value.
        DAQError
            If the module cannot be reached or is not an LDQ-412.
        """
        return cls(**cls.url_options(url), timeout=timeout, check_identity=check_identity)

    @abstractmethod
    def read_scans(self) -> list[Scan]:
        """Every scan since the previous call, exactly once, oldest first, at once.

        From the FIFO where the transport has one (Modbus), otherwise by polling the
        latest-scan snapshot once per call (ASCII, or Modbus with ``fifo=0``), in which
        case scans the device produced between two polls are reported in Scan.missed.
        Scans already taken off the device when a call fails are kept and returned by the
        next successful call. To read continuously at the module's pace, use
        :meth:`scans`.

        Returns
        -------
        list[Scan]
            The new scans (possibly none), oldest first.

        Raises
        ------
        DAQError
            DAQTimeout, DAQProtocolError, DAQModbusException or DAQDisconnected; the next
            call tries again.
        """

    def scans(self, timeout: float | None = None, duration: float | None = None) -> Iterator[Scan]:
        """Every scan, once and in order, as the module makes them: a stream.

        The module is read at its own pace: over a FIFO every
        :data:`~loopcal.drivers.pacing.FIFO_READ_PERIOD_S` (0.5 s), and without one
        (ASCII, Modbus ``fifo=0``) once per scan, each poll between two scans
        (:mod:`loopcal.drivers.pacing`); in between the stream sleeps. Scans the module
        made that were not read (FIFO overflow, polls that came too late) are reported in
        ``Scan.missed`` as by :meth:`read_scans`. Errors while waiting (a stall, a corrupted
        answer, a reconnect) are retried every 0.05 s until ``timeout`` runs out, since the
        next read recovers from them. Scans read but not yet yielded when the stream is
        closed early (``break``) are kept: the next :meth:`read_scans` or stream returns
        them first. ``for scan in daq`` is ``for scan in daq.scans()``.

        Parameters
        ----------
        timeout : float or None
            s without a new scan after which the stream raises DAQTimeout, counted from
            the stream's start, then from the newest scan's arrival (it is raised by the
            first read after that, which a failing driver may take its own timeout to
            answer). None: no limit on waiting for new scans, and a driver error is raised
            at once (nothing waits for it to clear).
        duration : float or None
            s after which the stream ends (after a last read, which brings the scans made
            until then); None: it does not end by itself.

        Returns
        -------
        Iterator[Scan]
            A generator of the scans, oldest first.

        Raises
        ------
        TypeError
            If ``timeout`` or ``duration`` is not a number or None.
        ValueError
            If ``timeout`` or ``duration`` is not finite and > 0 (at the call, before
            anything is read).
        DAQTimeout
            While iterating: no new scan within ``timeout`` s; chained from the driver's
            last error, if there was one.
        DAQError
            While iterating with ``timeout`` None: the driver's error; with any timeout:
            DAQDisconnected if the driver was closed.

        Examples
        --------
        >>> with open_daq("modbus-tcp://127.0.0.1:5020?unit=1") as daq:  # doctest: +SKIP
        ...     for scan in daq.scans(timeout=1.0, duration=10.0):
        ...         print(scan.counter64, scan.volts)
        """
        return self._stream(_seconds("timeout", timeout), _seconds("duration", duration))

    def __iter__(self) -> Iterator[Scan]:
        """``for scan in daq``: :meth:`scans` with no timeout and no end.

        Returns
        -------
        Iterator[Scan]
            The stream; a driver error ends it (raised).
        """
        return self.scans()

    def _stream(self, timeout: float | None, duration: float | None) -> Iterator[Scan]:
        start = time.monotonic()
        end = math.inf if duration is None else start + duration
        newest_at = start  # when the newest scan (or the stream's start) arrived
        pacer: FifoPacer | PollPacer | None = None
        at = start
        while True:
            if timeout is not None:
                at = min(at, newest_at + timeout)  # to notice the timeout when it runs out
            last = at >= end
            if last:
                at = end
            _sleep_until(at)
            if self.has_fifo and pacer is None:
                pacer = FifoPacer()
            elif not self.has_fifo and (pacer is None or pacer.rate_hz != self.scan_rate_hz):
                pacer = PollPacer(self.scan_rate_hz)
            sent = time.monotonic()
            try:
                batch = self.read_scans()
            except DAQError as exc:
                now = time.monotonic()
                if timeout is None or self._closed:
                    raise
                if now - newest_at >= timeout:
                    raise DAQTimeout(
                        f"{self.url}: no scan within {timeout:g} s "
                        f"(last error: {type(exc).__name__}: {exc})"
                    ) from exc
                if last or now >= end:
                    return
                at = now + STREAM_RETRY_S
                continue
            received = time.monotonic()
            pacer.observe(sent, received, batch)
            if batch:
                newest_at = received
            elif timeout is not None and received - newest_at >= timeout:
                raise DAQTimeout(f"{self.url}: no scan within {timeout:g} s")
            given = 0
            try:
                for scan in batch:
                    given += 1
                    yield scan
            finally:
                if given < len(batch):  # closed early: the next read returns the rest
                    self._pending[:0] = batch[given:]
            if last:
                return
            at = pacer.next_read(time.monotonic())

    @abstractmethod
    def snapshot(self) -> Scan:
        """The latest scan, with its measured time and status.

        Over a FIFO the scan is not taken off the FIFO, and the sequence is not moved on
        (read_scans still returns it); when polling, a new scan seen here is also
        returned by the next :meth:`read_scans`.

        Returns
        -------
        Scan
            ``source="snapshot"``.

        Raises
        ------
        DAQError
            As :meth:`read_scans`.
        """

    @property
    def has_fifo(self) -> bool:
        """True if :meth:`read_scans` drains the module's FIFO (every scan once, up to 256
        waiting); False if it polls the latest scan, so that a host must call it once per
        scan to miss none (as :meth:`scans` does)."""
        return False

    @property
    def scan_rate_hz(self) -> int:
        """The scan rate the driver works with, Hz (1..200), without a request: read from
        the module at connect, followed when set, and re-read when the scans' spacing
        shows that the module changed it (a power cycle restores the power-on rate). What
        a recorder stamps and a stream paces its polls by; :attr:`scan_rate` asks the
        module."""
        return self._seq.scan_rate_hz

    @property
    def sequencer(self) -> Sequencer:
        """The sequence state that links the driver's reads: ``restarts_detected``,
        ``missed_total``, ``epoch``, ``measured_period_us`` (read-only use)."""
        return self._seq

    @property
    def scan_rate(self) -> int:
        """The module's configured scan rate, Hz (1..200), read from it at each access.

        Setting it writes the module (over a FIFO the scans made at the old rate are
        read first: their derived times need it).

        Raises
        ------
        TypeError
            When set to anything but an int.
        ValueError
            When set outside 1..200 Hz.
        DAQError
            If the module cannot be read or written.
        """
        return self._get_scan_rate()

    @scan_rate.setter
    def scan_rate(self, hz: int) -> None:
        if not isinstance(hz, int) or isinstance(hz, bool):
            raise TypeError(f"scan rate must be an int (Hz), got {hz!r}")
        if not ldq412.SCAN_RATE_MIN_HZ <= hz <= ldq412.SCAN_RATE_MAX_HZ:
            raise ValueError(
                f"scan rate {hz} Hz outside {ldq412.SCAN_RATE_MIN_HZ}..{ldq412.SCAN_RATE_MAX_HZ}"
            )
        self._set_scan_rate(hz)

    @abstractmethod
    def _get_scan_rate(self) -> int: ...

    @abstractmethod
    def _set_scan_rate(self, hz: int) -> None: ...

    @abstractmethod
    def clear_restart(self) -> bool:
        """Clear the module's latched restart flag (status bit 9), after reading what is
        waiting so that no restart goes unreported.

        Returns
        -------
        bool
            True if cleared; False if the transport cannot (ASCII).

        Raises
        ------
        DAQError
            If the module cannot be read or written.
        """

    @abstractmethod
    def close(self) -> None:
        """Release the transport; every later call raises DAQDisconnected. Idempotent."""

    def __enter__(self: D) -> D:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url}>"
