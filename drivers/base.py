"""The abstract :class:`DAQ`: what every driver of the LDQ-412 gives, whatever its transport
(the records it returns, :class:`Scan` and :class:`Identity`, are
:mod:`loopcal.drivers.records`'s, exported here too; :func:`~loopcal.drivers.registry.open_daq`
opens one by URL).

A driver gives its scans two ways, as python-can's buses give messages: :meth:`DAQ.read_scans`
returns at once what arrived since the previous call, and :meth:`DAQ.scans` (``for scan in
daq``) is a stream that reads at the module's own pace (:mod:`loopcal.drivers.pacing`),
for a duration or until no scan comes within a timeout::

    with open_daq("ascii:///dev/ttyUSB0?addr=01") as daq:
        for scan in daq.scans(timeout=1.0, duration=60.0):
            print(scan.counter64, scan.volts)
"""

from __future__ import annotations

import math
import numbers
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from typing import ClassVar, TypeVar

from . import ldq412
from .errors import DAQError, DAQTimeout
from .pacing import FifoPacer, Pacer, PollPacer
from .records import Identity, Scan
from .sequence import Sequencer
from .url import DaqUrl

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


class DAQ(ABC):
    """An LDQ-412 module reached over one transport;
    :func:`~loopcal.drivers.registry.open_daq` opens one by URL.

    Every call is bounded in time by the timeout given at open (plus the transfer time
    of the answer) and either returns valid data or raises a DAQError; after an error
    the next call tries again (reconnecting if needed). A DAQ is not thread-safe: one
    thread (or one lock) per instance. Scans come by :meth:`read_scans` (what arrived
    since the previous call, at once) or by the stream :meth:`scans` (``for scan in
    daq``); a DAQ is a context manager that closes it.

    A driver subclass is declared for its scheme (an entry point of the group
    ``loopcal.drivers``, or :func:`~loopcal.drivers.registry.register_scheme`: see
    :mod:`loopcal.drivers.registry`), lists its :attr:`url_params`, turns a URL into its
    constructor's arguments (:meth:`url_options`), sets :attr:`identity`, :attr:`url` and
    the sequencer at connect, and implements :meth:`read_scans`, :meth:`snapshot`,
    :meth:`clear_restart`, :meth:`close`, :meth:`read_scan_rate` and
    :meth:`_write_scan_rate` (which :meth:`write_scan_rate` calls with a checked rate).

    Attributes
    ----------
    scheme : str
        The URL scheme the class is declared for (class attribute; the registry sets it
        from the entry point's name, or :func:`~loopcal.drivers.registry.register_scheme`'s).
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
        """Connect to the module a parsed URL describes (what
        :func:`~loopcal.drivers.registry.open_daq` calls).

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

    def _connect_and_identify(self, open_link: Callable[[], None], check_identity: bool) -> None:
        """At connect: open the link, read what the module is (:attr:`identity`) and its
        scan rate (the sequencer's); any error closes the driver before it is raised.

        Parameters
        ----------
        open_link : callable
            Opens the transport; raises a DAQError if it cannot.
        check_identity : bool
            Passed on to :meth:`_read_identity`.
        """
        try:
            open_link()
            self.identity = self._read_identity(check_identity)
            self._seq = Sequencer(self.read_scan_rate())
        except BaseException:
            self.close()
            raise

    def _read_identity(self, check: bool) -> Identity:
        """What the module says it is, read from it (for :meth:`_connect_and_identify`).

        Parameters
        ----------
        check : bool
            Raise DAQIdentityError unless the module is an LDQ-412.

        Returns
        -------
        Identity
        """
        raise NotImplementedError(f"{type(self).__name__} does not read an identity")

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
        pacer: Pacer | None = None
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
        a recorder stamps and a stream paces its polls by; :meth:`read_scan_rate` asks
        the module."""
        return self._seq.scan_rate_hz

    @property
    def sequencer(self) -> Sequencer:
        """The sequence state that links the driver's reads: ``restarts_detected``,
        ``missed_total``, ``epoch``, ``measured_period_us`` (read-only use)."""
        return self._seq

    @abstractmethod
    def read_scan_rate(self) -> int:
        """The module's configured scan rate, read from it (a request on the wire, where
        :attr:`scan_rate_hz` makes none).

        Returns
        -------
        int
            The rate, Hz (1..200).

        Raises
        ------
        DAQError
            If the module cannot be read, or answers a rate outside 1..200 Hz.
        """

    def write_scan_rate(self, hz: int) -> None:
        """Set the module's scan rate (a write on the wire); the driver follows it
        (:attr:`scan_rate_hz`). Over a FIFO the scans made at the old rate are read first,
        since their derived times need it: the next :meth:`read_scans` returns them.

        Parameters
        ----------
        hz : int
            The new rate, Hz (1..200).

        Raises
        ------
        TypeError
            If ``hz`` is not an int.
        ValueError
            If ``hz`` is outside 1..200 Hz.
        DAQError
            If the module cannot be read or written.
        """
        if not isinstance(hz, int) or isinstance(hz, bool):
            raise TypeError(f"scan rate must be an int (Hz), got {hz!r}")
        if not ldq412.SCAN_RATE_MIN_HZ <= hz <= ldq412.SCAN_RATE_MAX_HZ:
            raise ValueError(
                f"scan rate {hz} Hz outside {ldq412.SCAN_RATE_MIN_HZ}..{ldq412.SCAN_RATE_MAX_HZ}"
            )
        self._write_scan_rate(hz)

    @abstractmethod
    def _write_scan_rate(self, hz: int) -> None:
        """Write ``hz`` (checked: 1..200 Hz) to the module, and have the sequencer follow
        it (``self._seq.set_rate``)."""

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
