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


class FaultInjector:
    """Inject faults into an emulated module.

    on_link_change: called (from the caller's thread, without the lock held) after the
        link or power state changed, so that servers can follow at once (the TCP server
        resets connections and stops or resumes listening).
    """

    def __init__(self, handle: DeviceHandle, on_link_change: Callable[[], None]) -> None:
        self._handle = handle
        self._on_link_change = on_link_change

    def disconnect(self) -> None:
        """Cut the link until :meth:`reconnect`."""
        with self._handle.lock:
            self._handle.wire.disconnected = True
        self._on_link_change()

    def reconnect(self) -> None:
        """Restore the link."""
        with self._handle.lock:
            self._handle.wire.disconnected = False
        self._on_link_change()

    def stall(self, seconds: float) -> None:
        """The module stops answering for ``seconds`` of device-clock time."""
        if seconds < 0:
            raise ValueError("seconds must be >= 0")
        with self._handle.synced() as device:
            self._handle.wire.stalled_until_ns = device.now_ns + round(seconds * 1e9)

    def restart(self, off_s: float = POWER_CYCLE_S) -> None:
        """Power cycle: silent for ``off_s`` device seconds, then counter 0, restart bit."""
        with self._handle.synced() as device:
            device.power_cycle(off_s)
            self._handle.wire.stalled_until_ns = None
        self._on_link_change()

    def latency(self, latency: Latency | None) -> None:
        """Answers take ``latency`` from now on (None: sent at once)."""
        with self._handle.lock:
            self._handle.wire.latency = latency

    def garbage(self, nbytes: int) -> None:
        """Send ``nbytes`` junk bytes just before the next answer."""
        with self._handle.lock:
            self._handle.wire.add_garbage(nbytes)

    def corrupt_next(self, n: int = 1) -> None:
        """Break the next ``n`` answers (CRC, MBAP header or ASCII checksum/character)."""
        if n < 0:
            raise ValueError("n must be >= 0")
        with self._handle.lock:
            self._handle.wire.corrupt += n

    def stuck_channel(self, ch: int, code: int | None) -> None:
        """Channel ``ch`` (1..4) reports ``code`` from the next scan on; None releases it."""
        with self._handle.synced() as device:
            device.set_stuck(ch, code)

    def sensor_fault(self, ch: int, on: bool) -> None:
        """Sensor fault on channel ``ch`` (1..4): reads 4095 with its fault bit set."""
        with self._handle.synced() as device:
            device.set_sensor_fault(ch, on)

    def saturate(self, ch: int, level: str | None) -> None:
        """Channel ``ch``'s conditioner saturates at the "high" or "low" rail (None: not)."""
        with self._handle.synced() as device:
            device.set_saturation(ch, level)

    def clear(self) -> None:
        """End every fault (a power cycle under way still completes)."""
        with self._handle.synced() as device:
            device.clear_channel_faults()
            self._handle.wire.clear()
            was_disconnected = self._handle.wire.disconnected
            self._handle.wire.disconnected = False
        if was_disconnected:
            self._on_link_change()
