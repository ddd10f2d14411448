"""Is the module there, and what is it: :func:`probe` asks the module at a URL what it is,
and when it does not answer, finds out why, within a time budget (:data:`PROBE_BUDGET_S`).

What it does, in order, each step only while the budget lasts:

1. a serial device is looked at first (:func:`~loopcal.drivers.diagnosis.port_problem`):
   missing, not a device, not this user's to open, held by another process; a serial
   device server's TCP port (``ascii://HOST:PORT``) is connected to for a moment
   (:func:`~loopcal.drivers.diagnosis.server_problem`): refused, no answer, no route;
2. the URL as given is opened (identity read without refusing another model). If it
   answers: one scan (codes and volts, status: FIFO level and overflow, restart), the
   scan rate, and the round trip of five answers; another model is ``not_module``;
3. a connection that fails is explained by the error
   (:func:`~loopcal.drivers.diagnosis.diagnose`): refused, no answer from the host, no
   route; a TCP server that answers with something else is shown what it sent (an HTTP
   server's first line, an echo of the request);
4. when nothing answers (or only garbage arrives), the other settings are tried, the
   datasheet's defaults first (unit 1, address 01, 115200 baud), then the usual rates
   (:data:`USUAL_BAUDS`) and the other units or addresses, until one answers or the
   budget runs out: ``wrong_unit``, ``wrong_address``, ``wrong_checksum``, ``wrong_baud``
   name the setting that answers and the URL to use; else ``no_answer`` or ``garbled``
   (bytes, but never a valid frame). A device server's line is at the rate the device
   server is set to (pyserial ignores the URL's on a socket): no other rate is tried.

Every try is in the report (:attr:`ProbeReport.tried`). A try is started only if its worst
case (twice the answer timeout, and a margin; on a device server's line also the
:data:`SOCKET_CLOSE_S` pyserial waits after closing it) fits in what is left of the
budget, so a probe ends within the budget.

Over ASCII a carriage return is sent alone before each try: it ends whatever a try at
another rate left in the module's line buffer (garbage the module would otherwise take as
the start of the next command); an empty frame gets no answer. On a device server's line,
where every try is at one rate, only before the first (what another program left).
"""

from __future__ import annotations

import socket
import statistics
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from urllib.parse import urlencode

from . import ldq412
from .ascii import AsciiDAQ, encode_command, parse_scan
from .base import DAQ
from .diagnosis import Diagnosis, diagnose, endpoint, errno_of, port_problem, server_problem
from .errors import (
    DAQDisconnected,
    DAQError,
    DAQInvalidCommand,
    DAQModbusException,
    DAQProtocolError,
    DAQTimeout,
)
from .modbus import ModbusDAQ, parse_snapshot
from .registry import driver_for_url
from .url import DaqUrl, parse_url

#: s a probe may take in all (``loopcal probe`` answers within it, whatever the fault)
PROBE_BUDGET_S = 5.0
#: the line rates tried on a serial line that does not answer, the datasheet's first
USUAL_BAUDS = (ldq412.SERIAL_BAUD, 9600, 19200, 38400, 57600)
#: answers read to measure the round trip (each a snapshot: one scan of the module)
RTT_READS = 5
#: s kept in hand beyond a try's worst case before it is started (closing a port,
#: scheduling on a busy host)
MARGIN_S = 0.25
#: bytes of a non-Modbus server's answer kept for the report
PEEK_BYTES = 120
#: s pyserial waits after closing a device server's line (``socket://``, for a quick
#: reconnect): a try there that fails, and so closes it, costs that much more
SOCKET_CLOSE_S = 0.3


def with_params(url: DaqUrl, changes: dict[str, str]) -> str:
    """A URL with some query parameters set (the others kept, in their order).

    Parameters
    ----------
    url : DaqUrl
        The parsed URL.
    changes : dict of str to str
        Parameters to set (added at the end if the URL has none of that name).

    Returns
    -------
    str
        The URL as text.
    """
    params = {**url.params, **changes}
    return url.raw.split("?", 1)[0] + "?" + urlencode(params, safe="/")


@dataclass(frozen=True)
class Attempt:
    """One try of a probe: a URL opened, and what came of it.

    Attributes
    ----------
    url : str
        The URL tried.
    outcome : str
        ``answers``, ``no answer``, ``garbled`` (bytes, no valid frame), ``rejected``
        (an ASCII ``?AA``), ``exception`` (a Modbus exception), ``not an LDQ-412``,
        ``cannot connect`` or ``closed`` (connected, then closed by the other end).
    detail : str
        The driver's message, or what answered.
    elapsed_s : float
        How long the try took, s.
    """

    url: str
    outcome: str
    detail: str
    elapsed_s: float


@dataclass
class ProbeReport:
    """What a probe found: the module, or why not (:func:`probe`).

    Attributes
    ----------
    url : str
        The URL probed, as given.
    found : bool
        An LDQ-412 answers at the URL as given.
    cause : str or None
        None if found; else one of :data:`~loopcal.drivers.diagnosis.CAUSES`.
    message : str
        What was found, or what is wrong.
    hint : str
        What to do ("" if found and nothing is amiss).
    answered_url : str or None
        The URL at which an LDQ-412 answered: the URL given when found, another (the one
        to use) for ``wrong_unit``, ``wrong_baud`` and the like.
    identity : dict or None
        What answered says it is: ``model``, ``firmware``, ``serial`` (None over ASCII),
        ``model_code`` (None over ASCII).
    module : dict or None
        What it reads: ``scan_rate_hz``, ``fifo_level`` (None over ASCII), ``overflow``
        and ``restarted`` (the latched status bits), ``scan`` (``counter``, ``time_us``,
        ``codes``, ``volts``, ``status``, ``at_rail`` and ``sensor_fault`` channel
        numbers).
    rtt_ms : dict or None
        Round trip of the snapshot reads: ``median``, ``max`` (ms), ``n``.
    notes : list of str
        What else a user should know (a channel at the rail or in fault, answers slower
        than half the timeout).
    details : dict
        The diagnosis' facts (:attr:`~loopcal.drivers.diagnosis.Diagnosis.details`).
    tried : list of Attempt
        Every URL tried, in order.
    elapsed_s : float
        How long the probe took, s.
    budget_s : float
        Its budget, s.
    timeout_s : float
        How long each answer was waited for, s.
    """

    url: str
    found: bool
    cause: str | None
    message: str
    hint: str = ""
    answered_url: str | None = None
    identity: dict | None = None
    module: dict | None = None
    rtt_ms: dict | None = None
    notes: list[str] = field(default_factory=list)
    details: dict = field(default_factory=dict)
    tried: list[Attempt] = field(default_factory=list)
    elapsed_s: float = 0.0
    budget_s: float = PROBE_BUDGET_S
    timeout_s: float = ldq412.HOST_TIMEOUT_S

    def to_json(self) -> dict:
        """The report as one JSON-ready object (``loopcal probe --json``).

        Returns
        -------
        dict
            Every attribute, ``tried`` as a list of objects.
        """
        return asdict(self)

    @classmethod
    def of(cls, url: str, diagnosis: Diagnosis, **kw: object) -> ProbeReport:
        """A report of a cause.

        Parameters
        ----------
        url : str
            The URL probed.
        diagnosis : Diagnosis
            The cause.
        **kw
            Further attributes (``tried``, ``elapsed_s``, ...).

        Returns
        -------
        ProbeReport
            ``found`` False.
        """
        return cls(
            url,
            False,
            diagnosis.cause,
            diagnosis.message,
            diagnosis.hint,
            details=diagnosis.details,
            **kw,
        )  # type: ignore[arg-type]


_OUTCOMES = (
    (DAQInvalidCommand, "rejected"),
    (DAQTimeout, "no answer"),
    (DAQProtocolError, "garbled"),
    (DAQModbusException, "exception"),
    (DAQDisconnected, "cannot connect"),
)


def _outcome(exc: DAQError) -> str:
    if isinstance(exc, DAQDisconnected) and errno_of(exc)[1] is None:
        return "closed"  # connected, then the peer closed (the port's own errors are OSErrors)
    return next((word for kind, word in _OUTCOMES if isinstance(exc, kind)), "error")


def _ranges(values: list[int], fmt: str = "{}") -> str:
    """``1, 3-7, 9``: sorted integers as runs."""
    runs: list[list[int]] = []
    for v in sorted(set(values)):
        if runs and v == runs[-1][-1] + 1:
            runs[-1].append(v)
        else:
            runs.append([v])
    return ", ".join(
        fmt.format(r[0]) if len(r) == 1 else f"{fmt.format(r[0])}-{fmt.format(r[-1])}" for r in runs
    )


class _Prober:
    """One probe's state: the URL, its options, the deadline and the tries so far."""

    def __init__(self, url: str, timeout: float, budget: float) -> None:
        self.url = url
        self.cls, self.parsed = driver_for_url(url)
        ep = endpoint(url)
        self.options, self.serial, self.where, self.server = (
            ep.options, ep.serial, ep.where, ep.server
        )  # fmt: skip
        self.timeout = timeout
        self.budget = budget
        self.t0 = time.monotonic()
        self.deadline = self.t0 + budget
        self.tried: list[Attempt] = []

    # -- tries ----------------------------------------------------------------------------

    def affordable(self) -> bool:
        """Whether a try's worst case (two answer timeouts and the margin, and a device
        server's line closed) fits in the budget that is left."""
        closing = SOCKET_CLOSE_S if self.server else 0.0
        return self.deadline - time.monotonic() >= 2 * self.timeout + MARGIN_S + closing

    def attempt(self, changes: dict[str, str]) -> tuple[DAQ | None, DAQError | None, str]:
        """Open the URL with ``changes``: the driver (connected, identity read) or the error."""
        url = with_params(self.parsed, changes) if changes else self.url
        parsed = parse_url(url)
        if issubclass(self.cls, AsciiDAQ) and (self.server is None or not self.tried):
            self._clear_line(self.cls.url_options(parsed))
        t = time.monotonic()
        try:
            daq = self.cls.from_url(parsed, timeout=self.timeout, check_identity=False)
        except DAQError as exc:
            self.tried.append(Attempt(url, _outcome(exc), str(exc), time.monotonic() - t))
            return None, exc, url
        ident = daq.identity
        self.tried.append(
            Attempt(
                url,
                "answers" if self._is_module(daq) else "not an LDQ-412",
                f"{ident.model} firmware {ident.firmware}",
                time.monotonic() - t,
            )
        )
        return daq, None, url

    def _clear_line(self, options: dict) -> None:
        """A CR alone at the try's rate: ends what the module's line buffer holds."""
        import serial

        try:
            with serial.serial_for_url(
                str(options["port"]),
                int(options["baud"]),
                timeout=0,
                write_timeout=self.timeout,
                exclusive=True,
            ) as ser:
                ser.write(ldq412.ASCII_CR)
                ser.flush()
        except (serial.SerialException, OSError, ValueError):
            pass  # the try itself reports what is wrong with the port

    @staticmethod
    def _is_module(daq: DAQ) -> bool:
        ident = daq.identity
        if ident.model_code is not None:
            return ident.model_code == ldq412.MODEL_CODE
        return ident.model == ldq412.MODEL_NAME

    def candidates(self) -> Iterator[dict[str, str]]:
        """The other settings to try, most likely first: the datasheet's defaults, then
        the usual rates, then the other units or addresses."""
        o = self.options
        if self.cls.scheme == "ascii" or isinstance(o.get("addr"), int):
            key, mine, default, others = (
                "addr",
                int(o["addr"]),
                ldq412.ASCII_DEFAULT_ADDR,
                range(0, 256),
            )
            fmt = "{:02X}"
        else:
            key, mine, default, others = "unit", int(o["unit"]), ldq412.MODBUS_UNIT, range(1, 248)
            fmt = "{}"
        ids = [mine] + ([default] if default != mine else [])
        if not self.serial:
            order = [default, *(u for u in others if u != default)]
            yield from ({key: fmt.format(u)} for u in order if u != mine)
            return
        baud = int(o["baud"])
        seen = {(baud, mine)}
        if default != mine:
            seen.add((baud, default))
            yield {key: fmt.format(default)}
        if key == "addr":  # the module's checksum mode may be the other one
            yield {"checksum": "0" if o["checksum"] else "1"}
        for rate in USUAL_BAUDS if self.server is None else ():  # a device server: its own
            for unit in ids:
                if (rate, unit) not in seen:
                    seen.add((rate, unit))
                    yield {"baud": str(rate), key: fmt.format(unit)}
        yield from ({key: fmt.format(u)} for u in others if (baud, u) not in seen)

    # -- the probe ------------------------------------------------------------------------

    def run(self) -> ProbeReport:
        if self.serial:
            if self.server:
                problem = server_problem(*self.server, self.timeout)
            else:
                problem = port_problem(self.where)
            if problem is not None:
                return self.report(problem)
        daq, exc, _ = self.attempt({})
        if daq is not None:
            return self.found(daq, self.url)
        assert exc is not None
        if isinstance(exc, DAQDisconnected):
            if self.serial or errno_of(exc)[1] is not None:  # the port or connection failed
                return self.report(self.port_or(exc))
            return self.report(self.peek())  # connected, then closed on the request
        if isinstance(exc, DAQModbusException):
            return self.report(diagnose(exc, self.url, timeout=self.timeout))
        if not self.serial and isinstance(exc, DAQProtocolError):
            return self.report(self.peek())
        return self.search(exc)

    def port_or(self, exc: DAQError) -> Diagnosis:
        """What is wrong with the serial device, else what the error says."""
        found = port_problem(self.where) if self.serial and not self.server else None
        return found or diagnose(exc, self.url, timeout=self.timeout)

    def search(self, first: DAQError) -> ProbeReport:
        """The URL as given does not answer (or garbles): try the others."""
        for changes in self.candidates():
            if not self.affordable():
                break
            daq, exc, url = self.attempt(changes)
            if isinstance(exc, DAQDisconnected):  # the port or host went away meanwhile
                return self.report(self.port_or(exc))
            if daq is None:
                continue
            if not self._is_module(daq):
                daq.close()
                continue
            return self.found_elsewhere(daq, url, changes, first)
        return self.report(self.nothing_answers())

    def found(self, daq: DAQ, url: str) -> ProbeReport:
        """The LDQ-412 answers at ``url``: what it is and what it reads."""
        with daq:
            ident = daq.identity
            identity = {
                "model": ident.model,
                "firmware": ident.firmware,
                "serial": ident.serial,
                "model_code": ident.model_code,
            }
            if not self._is_module(daq):
                if ident.model_code is not None:
                    said = (
                        f"a Modbus device answers at {self.where} (unit {self.options['unit']}),"
                        f" but its model code (input register {ldq412.IR_MODEL}) is "
                        f"{ident.model_code:#06x}, not the LDQ-412's {ldq412.MODEL_CODE:#06x}"
                    )
                else:
                    said = (
                        f"a device answers at {self.where} (address {self.options['addr']:02X}),"
                        f" but it says it is {ident.model!r}, not {ldq412.MODEL_NAME!r}"
                    )
                hint = "is this the module's address? another device answers there"
                return self.report(Diagnosis("not_module", said, hint), identity=identity)
            try:
                module, rtts = self.read_module(daq)
            except DAQError as exc:
                return self.report(
                    Diagnosis(
                        "lost",
                        f"the LDQ-412 at {self.where} answered, then stopped: {exc}",
                        "a loose connection, or the module restarting: probe again",
                    ),
                    identity=identity,
                    answered_url=daq.url,
                )
        notes = self.notes(module, rtts)
        serial = "" if ident.serial is None else f", serial {ident.serial}"
        as_given = url == self.url
        report = ProbeReport(
            self.url,
            as_given,
            None,
            f"{ident.model} firmware {ident.firmware}{serial} answers at {url}",
            answered_url=url,
            identity=identity,
            module=module,
            rtt_ms={
                "median": round(statistics.median(rtts) * 1e3, 2),
                "max": round(max(rtts) * 1e3, 2),
                "n": len(rtts),
            },
            notes=notes,
        )
        return self.finish(report)

    def found_elsewhere(
        self, daq: DAQ, url: str, changes: dict[str, str], first: DAQError
    ) -> ProbeReport:
        """The URL as given does not answer, ``url`` does: which setting to change."""
        report = self.found(daq, url)
        if report.cause is not None:
            return report
        theirs = self.cls.url_options(parse_url(url))
        changes = {k: v for k, v in changes.items() if theirs[k] != self.options[k]}
        given, answered = self._describe(self.options, changes), self._describe(theirs, changes)
        garbled = isinstance(first, DAQProtocolError) and not isinstance(first, DAQInvalidCommand)
        how = " (bytes arrive, but no valid frame)" if garbled else ""
        if "baud" in changes or "checksum" in changes:
            report.cause = "wrong_baud" if "baud" in changes else "wrong_checksum"
            report.message = (
                f"no valid answer at {self.where} with {given}{how}; the module "
                f"answers with {answered}: use {url}"
            )
        else:
            report.cause = "wrong_address" if "addr" in changes else "wrong_unit"
            report.message = (
                f"{given} does not answer at {self.where}{how}; {answered} does: use {url}"
            )
        report.found = False
        report.hint = (
            f"put {urlencode(changes)} in the URL ([daq].url in the daemon's config), "
            f"or set the module to {given} as the URL says"
        )
        return report

    @staticmethod
    def _describe(options: dict, changes: dict[str, str]) -> str:
        words = []
        if "unit" in changes:
            words.append(f"unit {options['unit']}")
        if "addr" in changes:
            words.append(f"address {options['addr']:02X}")
        if "checksum" in changes:
            words.append(f"checksum {'on' if options['checksum'] else 'off'}")
        if "baud" in changes:
            words.append(f"{options['baud']} baud")
        return ", ".join(words)

    def read_module(self, daq: DAQ) -> tuple[dict, list[float]]:
        """One scan and the round trip of up to :data:`RTT_READS` answers (fewer if the
        budget runs short), read without changing anything on the module."""
        rtts: list[float] = []
        snap = None
        for _ in range(RTT_READS):
            if rtts and self.deadline - time.monotonic() < self.timeout + MARGIN_S:
                break
            t = time.monotonic()
            if isinstance(daq, ModbusDAQ):
                regs = daq.read_input_registers(ldq412.IR_COUNTER, ldq412.IR_SNAPSHOT_LEN)
                rtts.append(time.monotonic() - t)
                snap = parse_snapshot(regs)
            else:
                assert isinstance(daq, AsciiDAQ)
                body = daq.transact(encode_command("#", daq.addr, checksum=daq.checksum))
                rtts.append(time.monotonic() - t)
                snap = parse_scan(body, daq.addr)
        assert snap is not None
        volts = [round(float(ldq412.code_to_volts(c)), 4) for c in snap.codes]
        channels = range(1, ldq412.N_CHANNELS + 1)
        module = {
            "scan_rate_hz": daq.scan_rate_hz,
            "fifo_level": snap.fifo_level,
            "overflow": bool(snap.status & ldq412.STATUS_OVERFLOW),
            "restarted": bool(snap.status & ldq412.STATUS_RESTART),
            "scan": {
                "counter": snap.counter,
                "time_us": snap.time_us,
                "codes": list(snap.codes),
                "volts": volts,
                "status": snap.status,
                "at_rail": [c for c in channels if snap.status >> (c - 1) & 1],
                "sensor_fault": [c for c in channels if snap.status >> (c + 3) & 1],
            },
        }
        return module, rtts

    def notes(self, module: dict, rtts: list[float]) -> list[str]:
        out = []
        scan = module["scan"]
        if scan["sensor_fault"]:
            out.append(
                f"sensor fault on channel(s) {scan['sensor_fault']}: excitation lost or a cable cut"
            )
        elif scan["at_rail"]:
            out.append(f"channel(s) {scan['at_rail']} at the rail: the reading is not trustworthy")
        if max(rtts) > self.timeout / 2:
            out.append(
                f"answers take up to {max(rtts) * 1e3:.0f} ms, more than half the "
                f"{self.timeout * 1e3:.0f} ms timeout: raise [daq].timeout "
                "(loopcal record --timeout)"
            )
        return out

    def peek(self) -> Diagnosis:
        """What a TCP server that is not a Modbus one says to a Modbus request."""
        from pymodbus.framer import FramerSocket
        from pymodbus.pdu import DecodePDU
        from pymodbus.pdu.register_message import ReadInputRegistersRequest

        request = FramerSocket(DecodePDU(False)).buildFrame(
            ReadInputRegistersRequest(
                address=ldq412.IR_MODEL,
                count=ldq412.IR_IDENTITY_LEN,
                dev_id=int(self.options["unit"]),
                transaction_id=1,
            )
        )
        got, closed = b"", False
        try:
            with socket.create_connection(
                (self.options["host"], self.options["port"]), timeout=self.timeout
            ) as s:
                s.sendall(request)
                end = time.monotonic() + self.timeout
                while len(got) < PEEK_BYTES and (left := end - time.monotonic()) > 0:
                    s.settimeout(left)
                    chunk = s.recv(PEEK_BYTES - len(got))
                    if not chunk:
                        closed = True
                        break
                    got += chunk
        except TimeoutError:
            pass
        except OSError as exc:
            return Diagnosis(
                "closed",
                f"{self.where} accepts the connection, then fails on a "
                f"Modbus request: {exc.strerror or exc}",
                "not a Modbus TCP server?",
            )
        after = " and closed the connection" if closed else ""
        if not got:
            return Diagnosis(
                "closed",
                f"{self.where} accepts the connection but closes it on a "
                "Modbus request, with no answer",
                "not a Modbus TCP server, or one "
                "that takes no more clients (another master connected?)",
            )
        if got == request:
            said = "sends back what it is sent (an echo server)"
        else:
            said = f"sent {got[:60]!r}{'...' if len(got) > 60 else ''}{after}"
        return Diagnosis(
            "not_modbus",
            f"something answers at {self.where}, but not Modbus TCP: to a Modbus request it {said}",
            f"is this the module's address and port? Modbus TCP is port {ldq412.MODBUS_TCP_PORT}",
            {"received": got.hex()},
        )

    def nothing_answers(self) -> Diagnosis:
        """No setting answered: which were tried, and what came back."""
        garbled = [a for a in self.tried if a.outcome == "garbled"]
        options = [self.cls.url_options(parse_url(a.url)) for a in self.tried]
        key = "unit" if "unit" in self.options else "addr"
        fmt = "{}" if key == "unit" else "{:02X}"
        words = ("unit", "units") if key == "unit" else ("address", "addresses")
        by_rate: dict[int, set[int]] = {}
        for o in options:
            by_rate.setdefault(int(o.get("baud", 0)), set()).add(int(o[key]))
        groups: dict[tuple[int, ...], list[int]] = {}  # the same ids at several rates: one
        for rate, ids in sorted(by_rate.items()):
            groups.setdefault(tuple(sorted(ids)), []).append(rate)
        parts = []
        for ids, rates in groups.items():
            part = f"{words[len(ids) > 1]} {_ranges(list(ids), fmt)}"
            if self.serial and not self.server:
                part += f" at {', '.join(map(str, rates))} baud"
            parts.append(part)
        tried = "; ".join(parts)
        budget = (
            ""
            if len(self.tried) > 1 and self.affordable()
            else f"; the {self.budget:g} s budget allowed no more"
        )
        if garbled and self.serial:
            return Diagnosis(
                "garbled",
                f"bytes arrive on {self.where}, but no valid frame at "
                f"any setting tried ({tried}{budget})",
                "another device or "
                "protocol on the line (is this the module's port?), a parity the "
                "module does not use, or noise: ground, termination",
                {"garbled_tries": len(garbled)},
            )
        if self.server:
            hint = (
                "is the module powered, its RS-485 pair A/B the right way round, wired to "
                "this port of the device server, and the device server set to its baud rate "
                "and parity?"
            )
        elif self.serial:
            hint = (
                "is the module powered, its RS-485 pair A/B the right way round, and the "
                "adapter the one it is wired to? (`dmesg | tail` after plugging it in)"
            )
        else:
            hint = (
                "the host accepts connections, but no Modbus unit answers: a gateway "
                "whose serial side is down, or not the module's address?"
            )
        return Diagnosis(
            "no_answer",
            f"nothing answers at {self.where} within {self.timeout:g} s ({tried}{budget})",
            hint,
        )

    def report(self, diagnosis: Diagnosis, **kw: object) -> ProbeReport:
        return self.finish(ProbeReport.of(self.url, diagnosis, **kw))

    def finish(self, report: ProbeReport) -> ProbeReport:
        report.tried = list(self.tried)
        report.budget_s = self.budget
        report.timeout_s = self.timeout
        report.elapsed_s = round(time.monotonic() - self.t0, 4)
        return report


def probe(
    url: str, *, timeout: float = ldq412.HOST_TIMEOUT_S, budget: float = PROBE_BUDGET_S
) -> ProbeReport:
    """Is the LDQ-412 at ``url`` there, and what is it; if not, why not (module docstring).

    Nothing on the module is changed: its registers are read, never written (the restart
    and overflow flags stay as they are), and no scan is taken off its FIFO.

    Parameters
    ----------
    url : str
        A driver URL (:func:`~loopcal.drivers.registry.open_daq`'s).
    timeout : float
        s to wait for each answer (> 0; the datasheet's 0.1 s by default).
    budget : float
        s the whole probe may take (> 0); a try is started only if it fits.

    Returns
    -------
    ProbeReport
        ``found`` with what the module is and reads, or ``cause``, ``message`` and
        ``hint``; ``tried`` lists every try.

    Raises
    ------
    ValueError
        For a URL no driver takes (as :func:`~loopcal.drivers.registry.driver_for_url`),
        or a timeout or budget that is not > 0.
    """
    if not timeout > 0 or not budget > 0:
        raise ValueError(f"timeout and budget must be > 0 s, got {timeout} and {budget}")
    return _Prober(url, timeout, budget).run()
