"""The emulated LDQ-412 on a real wire: device model + server, in a background thread.

::

    with Emulator("modbus-tcp", clock=ManualClock()) as emu:
        daq = open_daq(emu.url)          # modbus-tcp://127.0.0.1:40123?unit=1
        emu.clock.advance(1.0)           # 20 scans happen
        emu.faults.restart()
        emu.truth                        # every scan the module produced

Transports:

- ``"modbus-tcp"``: pymodbus TCP server on ``host:port`` (port 0: a free port).
- ``"modbus-rtu"``: pymodbus RTU server on a pseudo-terminal; the driver opens the other
  end (``/dev/pts/N``) with pyserial.
- ``"ascii"``: the module's ASCII protocol on a pseudo-terminal, same arrangement.

A serial transport with ``line="tcp"`` is reached through a serial device server on
``host:port`` instead (:mod:`loopcal.simulator.device_server`): ``modbus-rtu://HOST:PORT``,
``ascii://HOST:PORT``.

Everything (servers, pty relay, a 10 ms housekeeping tick) runs on one asyncio loop in
one thread, started by :meth:`Emulator.start` and stopped by :meth:`Emulator.close`.
With a :class:`~loopcal.simulator.clock.ManualClock`, the same scenario, seed and request sequence
put the same bytes on the wire.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
from typing import Any

import numpy as np

from loopcal.drivers.ldq412 import (
    ASCII_DEFAULT_ADDR,
    MODBUS_UNIT,
    SCAN_RATE_DEFAULT_HZ,
    SERIAL_BAUD,
)

from .ascii_server import AsciiServer
from .choices import LINES, TRANSPORTS
from .clock import Clock, RealClock
from .device import LDQ412, TruthScan
from .device_server import DeviceServer
from .faults import FaultInjector
from .handle import DeviceHandle
from .modbus_server import ModbusRtuHost, ModbusTcpHost
from .open_points import OpenPoints
from .pty import PtyLink
from .source import SignalSource, TestSource
from .wire import WireFaults

_log = logging.getLogger(__name__)

TICK_S = 0.01
_START_TIMEOUT_S = 5.0
_STOP_TIMEOUT_S = 15.0
_GARBAGE_STREAM = 0x6A756E6B  # second seed word: the garbage rng differs from the source's
_LATENCY_STREAM = 0x6C617465  # and the answer delays' from both


def _reason(exc: BaseException) -> str:
    """Why the servers did not start, for :meth:`Emulator.start`'s message: an OS error's
    own words (a pty that cannot be opened), else the exception's message. A taken TCP port
    does not come here as an OS error: pymodbus logs it and raises a RuntimeError of its own
    without a cause ("Could not start listen"), which is why start() asks the OS first."""
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc)


class Emulator:
    """An emulated LDQ-412 reachable at :attr:`url`; a context manager.

    Nothing runs until :meth:`start` (or ``with``): then the servers answer on their own
    thread until :meth:`close`.

    Parameters
    ----------
    transport : {"modbus-tcp", "modbus-rtu", "ascii"}
        The wire: a TCP socket, or a pseudo-terminal a driver opens with pyserial.
    source : SignalSource or None, default None
        The analog inputs; None: :class:`~loopcal.simulator.source.TestSource` (``seed``).
    scan_rate_hz : int, default 20
        Power-on value of holding register 0, the scan rate, 1..200 Hz.
    clock : Clock or None, default None
        The module's time base; None: :class:`~loopcal.simulator.clock.RealClock`.
    seed : int, default 0
        Seeds the built-in source, the garbage bytes and the answer delays (three
        separate streams).
    serial_number : int, default 0x00C0FFEE
        Serial number, uint32 (input registers 514-515).
    firmware : tuple of 2 int, default (2, 1)
        Firmware version (major, minor).
    unit : int, default 1
        Modbus unit id, 1..247 (requests for another unit get no answer).
    ascii_addr : int, default 0x01
        ASCII module address, 0..255.
    ascii_checksum : bool, default False
        Power-on value of holding register 4, the ASCII checksum mode.
    baud : int, default 115200
        The serial transports' line rate, baud: a driver that opens the pseudo-terminal at
        another rate reads garbage and is not understood (:mod:`loopcal.simulator.pty`).
    initial_uptime_s : float, default 0.0
        The module was powered on this long ago, s (for 32-bit wraps); only the last 256
        scans of that time exist (in the FIFO, overflow latched if more).
    host : str, default "127.0.0.1"
        TCP listening address (modbus-tcp, or a serial transport's device server).
    port : int, default 0
        TCP port (as ``host``); 0: a free port, reported in :attr:`port` and :attr:`url`
        once started.
    truth_limit : int or None, default None
        None keeps every scan in :attr:`truth`; N keeps at least the latest N (bounded
        memory for long real-time runs).
    open_points : OpenPoints or None, default None
        The choices the datasheet leaves open (:mod:`loopcal.simulator.open_points`: scan
        phase, clock error, answer latency, FIFO underrun, accepted reads); None is the
        emulator as it always was.
    device : LDQ412 or None, default None
        A device model to serve instead of a new
        :class:`~loopcal.simulator.device.LDQ412` (a replay's); source, scan_rate_hz,
        serial_number, firmware, ascii_checksum, initial_uptime_s, truth_limit and the
        open points other than the latency are then the device's own.
    line : {"pty", "tcp"}, default "pty"
        A serial transport's line: a pair of pseudo-terminals, or raw TCP through a serial
        device server on ``host:port`` (:mod:`loopcal.simulator.device_server`: no line
        rate, the link cut or a module off leave the connection open and silent).

    Attributes
    ----------
    transport : str
        As given.
    line : str
        As given ("pty" for modbus-tcp, which has no serial line).
    clock : Clock
        The time base in use.
    source : SignalSource
        The analog inputs (not used by a ``device`` given).
    device : LDQ412
        The device model served. Read it holding :attr:`lock`.
    faults : FaultInjector
        Fault injection (:mod:`loopcal.simulator.faults`): disconnect, stall, restart,
        garbage, corruption, channel faults, latency.
    url : str
        What :func:`loopcal.drivers.open_daq` opens, e.g.
        ``modbus-tcp://127.0.0.1:40123?unit=1``,
        ``modbus-rtu:///dev/pts/7?baud=115200&unit=1`` or
        ``ascii:///dev/pts/7?baud=115200&addr=01&checksum=0`` (``line="tcp"``:
        ``ascii://127.0.0.1:40124?...``); empty until started.
    port : int
        The TCP port (the one picked once started, for port 0).
    host : str
        As given.
    unit : int
        As given.
    ascii_addr : int
        As given.
    baud : int
        As given.
    open_points : OpenPoints
        As given (None: ``OpenPoints()``); the wire takes its latency from it.
    wire : WireFaults
        The wire fault state the servers consult.
    handle : DeviceHandle
        Serialized, clock-synced access to the device and the wire.

    Raises
    ------
    ValueError
        If ``transport``, ``unit`` or ``ascii_addr`` is out of range, or the device model
        refuses its settings (:class:`~loopcal.simulator.device.LDQ412`).

    Notes
    -----
    Everything (servers, pty relay, a 10 ms housekeeping tick that keeps the module
    scanning and the TCP endpoint following power and link state) runs on one asyncio
    loop in one thread. With a :class:`~loopcal.simulator.clock.ManualClock`, the same
    scenario, seed and request sequence put the same bytes on the wire.
    """

    def __init__(
        self,
        transport: str,
        source: SignalSource | None = None,
        *,
        scan_rate_hz: int = SCAN_RATE_DEFAULT_HZ,
        clock: Clock | None = None,
        seed: int = 0,
        serial_number: int = 0x00C0FFEE,
        firmware: tuple[int, int] = (2, 1),
        unit: int = MODBUS_UNIT,
        ascii_addr: int = ASCII_DEFAULT_ADDR,
        ascii_checksum: bool = False,
        baud: int = SERIAL_BAUD,
        initial_uptime_s: float = 0.0,
        host: str = "127.0.0.1",
        port: int = 0,
        truth_limit: int | None = None,
        open_points: OpenPoints | None = None,
        device: LDQ412 | None = None,
        line: str = LINES[0],
    ) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
        if line not in LINES:
            raise ValueError(f"line must be one of {LINES}, got {line!r}")
        if not 1 <= unit <= 247:
            raise ValueError("unit must be 1..247")
        if not 0 <= ascii_addr <= 0xFF:
            raise ValueError("ascii_addr must be 0..255")
        self.transport = transport
        self.line = line if transport != "modbus-tcp" else LINES[0]
        self.clock: Clock = clock if clock is not None else RealClock()
        self.source: SignalSource = source if source is not None else TestSource(seed)
        self.unit = unit
        self.ascii_addr = ascii_addr
        self.baud = baud
        self.host = host
        self.port = port
        self.open_points = open_points if open_points is not None else OpenPoints()
        self.device = device or LDQ412(
            self.source,
            now_ns=self.clock.now_ns(),
            scan_rate_hz=scan_rate_hz,
            serial_number=serial_number,
            firmware=firmware,
            ascii_checksum=ascii_checksum,
            initial_uptime_s=initial_uptime_s,
            truth_limit=truth_limit,
            open_points=self.open_points,
        )
        self.wire = WireFaults(
            rng=np.random.default_rng([seed, _GARBAGE_STREAM]),
            latency=self.open_points.latency,
            latency_rng=np.random.default_rng([seed, _LATENCY_STREAM]),
        )
        self.handle = DeviceHandle(self.device, self.clock, self.wire)
        self.faults = FaultInjector(self.handle, self._follow_link_state)
        self.url = ""

        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._startup_error: BaseException | None = None
        self._tcp: ModbusTcpHost | None = None
        self._rtu: ModbusRtuHost | None = None
        self._ascii: AsciiServer | None = None
        self._link: PtyLink | None = None
        self._device_server: DeviceServer | None = None
        self._reconcile_lock: asyncio.Lock | None = None

    # ------------------------------------------------------------------ public

    @property
    def first_request(self) -> threading.Event:
        """An event set once a server has handled its first request (a driver is talking)."""
        return self.handle.requested

    @property
    def link(self) -> PtyLink | None:
        """The null-modem link of a serial module (its byte counts), None over TCP or
        before :meth:`start`."""
        return self._link

    @property
    def lock(self) -> threading.RLock:
        """The lock to hold to read :attr:`device` consistently while the servers run.

        A re-entrant lock. Do not call :attr:`faults` methods while holding it: link and
        power changes wait for the server thread, which needs the lock.
        """
        return self.handle.lock

    @property
    def truth(self) -> list[TruthScan]:
        """Every scan the module produced so far, in order (a copy, synced to the clock).

        A list of :class:`~loopcal.simulator.device.TruthScan`; with ``truth_limit``, only
        the latest of them.
        """
        with self.handle.synced() as device:
            return list(device.truth)

    def take_truth(self) -> list[TruthScan]:
        """The scans produced since the last call, removed from :attr:`truth`.

        For long runs that keep the ground truth elsewhere.

        Returns
        -------
        list of TruthScan
            The scans the module kept since the last call (or since it was created), in
            order; :attr:`truth` is empty afterwards.
        """
        with self.handle.synced() as device:
            out, device.truth = device.truth, []
            return out

    @property
    def running(self) -> bool:
        """Whether the emulator's thread is alive (started and not closed)."""
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> Emulator:
        """Start the servers; returns once :attr:`url` is reachable. Idempotent.

        Returns
        -------
        Emulator
            ``self``.

        Raises
        ------
        RuntimeError
            If the TCP port is taken (``cannot listen on HOST:PORT: ...``) or the servers
            failed to start (a pseudo-terminal that cannot be opened, say); the message
            says why.
        TimeoutError
            If the servers were not up within 5 s.
        """
        if self._thread is not None:
            return self
        if self._on_tcp and self.port:
            # pymodbus reports a taken port only as "could not start listen": ask the OS
            try:
                with socket.create_server((self.host, self.port), reuse_port=False):
                    pass
            except OSError as exc:
                raise RuntimeError(
                    f"cannot listen on {self.host}:{self.port}: {exc.strerror or exc}"
                ) from None
        ready = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(ready,), name=f"ldq412-emulator[{self.transport}]", daemon=True
        )
        self._thread.start()
        if not ready.wait(_START_TIMEOUT_S):
            self.close()
            raise TimeoutError("emulator did not start")
        if self._startup_error is not None:
            err = self._startup_error
            self.close()
            where = f" on {self.host}:{self.port}" if self._on_tcp else ""
            raise RuntimeError(f"emulator failed to start{where}: {_reason(err)}") from err
        return self

    def close(self) -> None:
        """Stop the servers and the thread, close every fd. Idempotent.

        TCP clients see an orderly close; the pseudo-terminals go away.

        Raises
        ------
        RuntimeError
            If called from the emulator's own thread, or the thread did not stop within
            15 s (a loaded machine's server shutdown has taken over 5).
        """
        if self._thread is not None and threading.current_thread() is self._thread:
            raise RuntimeError("Emulator.close() called from the emulator's own thread")
        thread, self._thread = self._thread, None
        if thread is None:
            return
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None:
            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(stop.set)
        thread.join(_STOP_TIMEOUT_S)
        if thread.is_alive():
            raise RuntimeError("emulator thread did not stop")

    def __enter__(self) -> Emulator:
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Emulator({self.transport!r}, url={self.url!r})"

    @property
    def _on_tcp(self) -> bool:
        """Whether it listens on ``host:port`` (Modbus TCP, or a device server's line)."""
        return self.transport == "modbus-tcp" or self.line == "tcp"

    # ------------------------------------------------------------------ thread

    def _run(self, ready: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._main(ready))
        finally:
            pending = asyncio.all_tasks(loop)
            for task in pending:
                task.cancel()
            if pending:
                loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()
            ready.set()

    async def _main(self, ready: threading.Event) -> None:
        self._stop = asyncio.Event()
        self._reconcile_lock = asyncio.Lock()
        try:
            await self._open()
        except BaseException as exc:  # reported to start()'s caller
            self._startup_error = exc
            await self._teardown()
            ready.set()
            return
        ready.set()
        tick = asyncio.create_task(self._tick())
        await self._stop.wait()
        tick.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await tick
        await self._teardown()

    async def _open(self) -> None:
        loop = asyncio.get_running_loop()
        if self.transport == "modbus-tcp":
            self._tcp = ModbusTcpHost(self.handle, self.unit, self.host, self.port)
            await self._tcp.listen()
            self.port = self._tcp.port
            self.url = f"modbus-tcp://{self.host}:{self.port}?unit={self.unit}"
            return
        line = f"baud={self.baud}"
        ident = (f"unit={self.unit}" if self.transport == "modbus-rtu" else
                 f"addr={self.ascii_addr:02X}&checksum={int(self.device.power_on_ascii_checksum)}")
        if self.line == "tcp":
            self._device_server = DeviceServer(self.handle, self.transport, unit=self.unit,
                                               ascii_addr=self.ascii_addr, host=self.host,
                                               port=self.port)  # fmt: skip
            await self._device_server.listen()
            self.port = self._device_server.port
            self.url = f"{self.transport}://{self.host}:{self.port}?{line}&{ident}"
            return
        self._link = PtyLink(self.baud)
        self._link.start(loop, connected=lambda: not self.wire.disconnected)
        if self.transport == "modbus-rtu":
            self._rtu = ModbusRtuHost(self.handle, self.unit, self._link.device_path, self.baud)
            await self._rtu.listen()
        else:
            self._ascii = AsciiServer(self.handle, self._link.device_fd, self.ascii_addr)
            self._ascii.start(loop)
        self.url = f"{self.transport}://{self._link.host_path}?{line}&{ident}"

    async def _teardown(self) -> None:
        if self._tcp is not None:
            self._tcp.close()  # clients see an orderly close (FIN)
        if self._rtu is not None:
            self._rtu.close()
        if self._ascii is not None:
            self._ascii.close()
        if self._device_server is not None:
            self._device_server.close()
        if self._link is not None:
            self._link.close()
        await asyncio.sleep(0)  # let transports deliver connection_lost before the loop ends

    async def _tick(self) -> None:
        """Housekeeping: keep scanning (truth grows even if nobody reads) and let the
        TCP endpoint follow power and link state."""
        while True:
            await asyncio.sleep(TICK_S)
            try:
                await self._reconcile()
            except Exception:  # keep ticking: a failed re-listen is retried next tick
                _log.exception("emulator housekeeping failed")

    async def _reconcile(self) -> None:
        assert self._reconcile_lock is not None
        async with self._reconcile_lock:
            with self.handle.synced() as device:
                powered, boot = device.powered, device.boot
                disconnected = self.wire.disconnected
            tcp = self._tcp
            if tcp is None:
                return
            if disconnected or (powered and boot != self.handle.links_boot):
                tcp.reset_connections()
            if powered:
                self.handle.links_boot = boot
            want_listening = powered and not disconnected
            if want_listening and not tcp.listening:
                await tcp.listen()
            elif not want_listening and tcp.listening:
                tcp.stop_listening()

    def _follow_link_state(self) -> None:
        """Called by the fault injector: apply link/power changes before returning."""
        loop = self._loop
        if loop is None or not self.running or loop.is_closed():
            return
        if threading.current_thread() is self._thread:
            loop.create_task(self._reconcile())
            return
        future = asyncio.run_coroutine_threadsafe(self._reconcile(), loop)
        future.result(_STOP_TIMEOUT_S)
