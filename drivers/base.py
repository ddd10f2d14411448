"""Abstract DAQ interface and URL -> driver dispatch (the records a driver returns,
:class:`Scan` and :class:`Identity`, are :mod:`loopcal.drivers.records`'s, exported here too).

A driver is chosen by the scheme of a URL, as pyserial's ``serial_for_url`` and
python-can's interfaces do::

    modbus-tcp://host:port?unit=1[&fifo=1]
    modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1[&parity=N&stopbits=1&fifo=1]
    ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=1

Drivers register their scheme with :func:`register_scheme`; :func:`open_daq` parses the
URL, rejects unknown query parameters, and hands the parsed URL to the driver class.
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
    """A parsed driver URL.

    scheme: lower-case scheme, e.g. "modbus-tcp".
    host, port: network endpoint (None for serial URLs).
    path: serial device path (e.g. "/dev/ttyUSB0", "COM3"), "" for network URLs.
    params: query parameters, all values as strings.
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
        """Integer query parameter, or default if absent. Raises ValueError if malformed or
        outside ``lo..hi``."""
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
        """Query parameter that must be one of ``choices`` (case-insensitive)."""
        value = self.params.get(key)
        if value is None:
            return default
        if value.upper() not in choices:
            raise ValueError(f"{self.raw}: {key}={value!r} is not one of {', '.join(choices)}")
        return value.upper()

    def get_bool(self, key: str, default: bool) -> bool:
        """0/1 (also false/true, no/yes, off/on) query parameter."""
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
    """Split a driver URL into scheme, endpoint and query parameters.

    Raises ValueError on a missing scheme, a repeated query key, or a malformed port.
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
    """The serial line a URL names, every value checked: ``port`` (the URL's path),
    ``baud``, ``parity``, ``stopbits`` (datasheet defaults 115200, 8N1). example: a URL of
    the scheme with a port, for the error if the URL has none. Raises ValueError naming
    the URL."""
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
    """Class decorator: make ``open_daq`` dispatch URLs with ``scheme`` to the class."""

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
    """A copy of the scheme -> driver class registry."""
    _load_builtin()
    return dict(_REGISTRY)


def driver_for_url(url: str) -> tuple[type[DAQ], DaqUrl]:
    """The driver class a URL names and the parsed URL, without connecting.

    Raises ValueError for a malformed URL, an unknown scheme or an unknown query parameter.
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

    timeout: s without an answer before a call raises DAQTimeout (datasheet: 0.1 s).
    check_identity: raise DAQIdentityError unless the module identifies as an LDQ-412.

    Raises ValueError for an unknown scheme or bad/unknown query parameters, and the
    driver's DAQError subclasses for connection/identity failures.
    """
    cls, parsed = driver_for_url(url)
    if not timeout > 0:
        raise ValueError(f"timeout must be > 0 s, got {timeout}")
    return cls.from_url(parsed, timeout=timeout, check_identity=check_identity)


class DAQ(ABC):
    """An LDQ-412 module reached over one transport.

    Every call is bounded in time by the timeout given at open (plus the transfer time
    of the answer) and either returns valid data or raises a DAQError; after an error
    the next call tries again (reconnecting if needed). A DAQ is not thread-safe: one
    thread (or one lock) per instance.
    """

    scheme: ClassVar[str] = ""
    #: query parameters accepted in the URL
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
        """The constructor's keyword arguments that a parsed URL gives, every value checked
        without connecting. Raises ValueError naming the URL, the parameter and the value."""
        return {}

    @classmethod
    def from_url(cls, url: DaqUrl, *, timeout: float, check_identity: bool) -> DAQ:
        """Connect to the module the parsed URL describes (used by open_daq)."""
        return cls(**cls.url_options(url), timeout=timeout, check_identity=check_identity)

    @abstractmethod
    def read_scans(self) -> list[Scan]:
        """Every scan since the previous call, exactly once, oldest first.

        From the FIFO where the transport has one (Modbus), otherwise by polling the
        latest-scan snapshot once per call (ASCII, or Modbus with ``fifo=0``), in which
        case scans the device produced between two polls are reported in Scan.missed.
        Scans already taken off the device when a call fails are kept and returned by the
        next successful call.
        """

    def scans(self, timeout: float | None = None, duration: float | None = None) -> Iterator[Scan]:
        """Every scan, once and in order, as the module makes them: a stream.

        The module is read at its own pace: over a FIFO every
        :data:`~loopcal.drivers.pacing.FIFO_READ_PERIOD_S` (0.2 s), and without one
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
            s without a new scan after which the stream raises DAQTimeout (from the start,
            or from the newest scan); None waits for scans for ever, and then a driver
            error is raised at once (nothing waits for it to clear).
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
        """``for scan in daq``: :meth:`scans` with no timeout and no end."""
        return self.scans()

    def _stream(self, timeout: float | None, duration: float | None) -> Iterator[Scan]:
        start = time.monotonic()
        end = math.inf if duration is None else start + duration
        newest_at = start  # when the newest scan (or the stream's start) arrived
        pacer: FifoPacer | PollPacer | None = None
        at = start
        while True:
            last = at >= end
            if last:
                at = end
            if timeout is not None:
                at = min(at, newest_at + timeout)  # to notice the timeout when it runs out
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
        """The latest scan (measured time and status)."""

    @property
    def has_fifo(self) -> bool:
        """True if read_scans drains the module's FIFO (every scan once, up to 256 waiting);
        False if it polls the latest scan, so that a host must call it more often than the
        module scans to miss none."""
        return False

    @property
    def scan_rate_hz(self) -> int:
        """The scan rate the driver works with, Hz, without a request: read from the module
        at connect, followed when set, and re-read when the scans' spacing shows that the
        module changed it (a power cycle restores the power-on rate). What a recorder
        stamps and expects; :attr:`scan_rate` asks the module."""
        return self._seq.scan_rate_hz

    @property
    def sequencer(self) -> Sequencer:
        """Sequence state (restarts detected, total missed); read-only use."""
        return self._seq

    @property
    def scan_rate(self) -> int:
        """Configured scan rate, Hz (read from the module)."""
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
        """Clear the module's latched restart flag; False if the transport cannot."""

    @abstractmethod
    def close(self) -> None:
        """Release the transport. Idempotent."""

    def __enter__(self: D) -> D:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url}>"
