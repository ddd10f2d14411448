"""Fault injection on a running emulator (``Emulator.faults``).

Every method is safe to call from any thread and takes effect at the emulator clock's
current time. Link faults (disconnect, stall, garbage, corruption) act on the wire;
channel faults (stuck, sensor fault, saturation) act on the conversions of the following
scans and are physical: they survive a power cycle.

Meaning of each fault, where the contract leaves room:

- ``disconnect()``: the cable is cut. Serial: every byte in either direction is lost.
  TCP: established connections are reset and new ones refused until ``reconnect()``.
  The module keeps scanning (the FIFO fills and overflows as usual).
- ``stall(seconds)``: the module ignores requests (no answer, no effect, a FIFO read pops
  nothing) for ``seconds`` of device-clock time; it keeps scanning. A power cycle ends it.
- ``restart()``: power cycle. Off for 2 s of device-clock time (silent, no scans; on TCP
  new connections are refused and established ones stay silent, then get reset when the
  module is back), then power-on state: counter 0, device time 0, FIFO empty, restart
  bit set, holding registers back to their power-on values.
- ``garbage(nbytes)``: seeded random bytes go out just before the next answer.
- ``corrupt_next(n)``: the next n answers carry a broken CRC (RTU), a broken MBAP
  protocol identifier (TCP) or a broken checksum / non-hex character (ASCII).
- ``latency(Latency | None)``: from now on answers take this long (a burst of slow
  answers; None: at once). Not ended by ``clear()``.
- ``clear()``: ends every fault above except a power cycle already under way.
"""

from __future__ import annotations

from collections.abc import Callable

from loopcal.drivers.ldq412 import POWER_CYCLE_S

from .handle import DeviceHandle
from .open_points import Latency
from .wire import check_not_negative


class FaultInjector:
    """Inject faults into an emulated module (``Emulator.faults``).

    Every method is safe to call from any thread and acts at the emulator clock's current
    time (module docstring: what each fault means). Device-clock durations are device
    seconds: with a clock running ``speed`` times as fast they take ``1 / speed`` as long.

    Parameters
    ----------
    handle : DeviceHandle
        The emulator's device, clock and wire, behind its lock.
    on_link_change : callable
        Called with no arguments (from the caller's thread, without the lock held) after
        the link or power state changed, so that servers can follow at once (the TCP
        server resets connections and stops or resumes listening).
    """

    def __init__(self, handle: DeviceHandle, on_link_change: Callable[[], None]) -> None:
        self._handle = handle
        self._on_link_change = on_link_change

    def disconnect(self) -> None:
        """Cut the link until :meth:`reconnect` (or :meth:`clear`).

        Serial: every byte in either direction is lost (behind a serial device server,
        ``line="tcp"``, its connections stay open and unanswered). TCP: established
        connections are reset and new ones refused. The module keeps scanning.
        """
        with self._handle.lock:
            self._handle.wire.disconnected = True
        self._on_link_change()

    def reconnect(self) -> None:
        """Restore the link (TCP: listening again)."""
        with self._handle.lock:
            self._handle.wire.disconnected = False
        self._on_link_change()

    def stall(self, seconds: float) -> None:
        """The module stops answering for ``seconds`` of device-clock time.

        It ignores requests (no answer, no effect: a FIFO read pops nothing) and keeps
        scanning. A power cycle or :meth:`clear` ends it; a new stall replaces the old.

        Parameters
        ----------
        seconds : float
            How long, device seconds from now, >= 0.

        Raises
        ------
        ValueError
            If ``seconds`` is negative.
        """
        check_not_negative("seconds", seconds)
        with self._handle.synced() as device:
            self._handle.wire.stalled_until_ns = device.now_ns + round(seconds * 1e9)

    def restart(self, off_s: float = POWER_CYCLE_S) -> None:
        """Power cycle: silent for ``off_s`` device seconds, then the power-on state.

        Scans due up to now are taken first; a stall ends. Back on: counter 0, device time
        0, FIFO empty, restart bit set, holding registers at their power-on values
        (channel faults are physical and stay). Over TCP, new connections are refused
        while off and established ones reset once it is back.

        Parameters
        ----------
        off_s : float, default POWER_CYCLE_S
            How long it is off, device seconds (the datasheet's 2 s by default).
        """
        with self._handle.synced() as device:
            device.power_cycle(off_s)
            self._handle.wire.stalled_until_ns = None
        self._on_link_change()

    def latency(self, latency: Latency | None) -> None:
        """Answers take ``latency`` from now on (a burst of slow answers, say).

        Not ended by :meth:`clear`: set None to end it.

        Parameters
        ----------
        latency : Latency or None
            How long each answer waits (:class:`~loopcal.simulator.open_points.Latency`,
            wall-clock ms); None: sent at once.
        """
        with self._handle.lock:
            self._handle.wire.latency = latency

    def garbage(self, nbytes: int) -> None:
        """Send ``nbytes`` junk bytes just before the next answer.

        Parameters
        ----------
        nbytes : int
            How many seeded random bytes, >= 0 (added to any still pending).

        Raises
        ------
        ValueError
            If ``nbytes`` is negative.
        """
        with self._handle.lock:
            self._handle.wire.add_garbage(nbytes)

    def corrupt_next(self, n: int = 1) -> None:
        """Break the next ``n`` answers.

        A broken CRC (RTU), a broken MBAP protocol identifier (TCP), or a wrong checksum
        or a non-hex character (ASCII; :func:`~loopcal.simulator.wire.corrupt_ascii`).

        Parameters
        ----------
        n : int, default 1
            How many answers, >= 0 (added to any still pending).

        Raises
        ------
        ValueError
            If ``n`` is negative.
        """
        check_not_negative("n", n)
        with self._handle.lock:
            self._handle.wire.corrupt += n

    def stuck_channel(self, ch: int, code: int | None) -> None:
        """Channel ``ch`` reports ``code`` from the next scan on; None releases it.

        Parameters
        ----------
        ch : int
            1..4.
        code : int or None
            The code, 0..4095, or None.

        Raises
        ------
        ValueError
            If ``ch`` is not 1..4 or ``code`` not 0..4095.
        """
        with self._handle.synced() as device:
            device.set_stuck(ch, code)

    def sensor_fault(self, ch: int, on: bool) -> None:
        """Sensor fault on channel ``ch``: it reads 4095 with its fault bit set.

        Parameters
        ----------
        ch : int
            1..4.
        on : bool
            True from the next scan on; False ends it.

        Raises
        ------
        ValueError
            If ``ch`` is not 1..4.
        """
        with self._handle.synced() as device:
            device.set_sensor_fault(ch, on)

    def saturate(self, ch: int, level: str | None) -> None:
        """Channel ``ch``'s conditioner saturates at the high or the low rail.

        Parameters
        ----------
        ch : int
            1..4.
        level : {"high", "low"} or None
            ``"high"``: code 4095; ``"low"``: code 0; None ends it.

        Raises
        ------
        ValueError
            If ``ch`` is not 1..4 or ``level`` is none of those.
        """
        with self._handle.synced() as device:
            device.set_saturation(ch, level)

    def clear(self) -> None:
        """End every fault but the latency (a power cycle under way still completes).

        Ends a cut link, a stall, pending garbage and corruption, and stuck, faulted and
        saturated channels. The latency stays: :meth:`latency` with None ends it.
        """
        with self._handle.synced() as device:
            device.clear_channel_faults()
            self._handle.wire.clear()
            was_disconnected = self._handle.wire.disconnected
            self._handle.wire.disconnected = False
        if was_disconnected:
            self._on_link_change()
