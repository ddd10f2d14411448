"""The device model, its clock and the wire faults behind one lock.

Servers (in the emulator's thread) and fault injection or ground-truth reads (in the
caller's thread) both go through a :class:`DeviceHandle`, which serializes access and
brings the model up to the clock's time first.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

from .clock import Clock, HeldClock
from .device import LDQ412
from .wire import WireFaults


class DeviceHandle:
    """Serialized, clock-synced access to an :class:`LDQ412` and its :class:`WireFaults`.

    Parameters
    ----------
    device : LDQ412
        The device model.
    clock : Clock
        Its time base (a :class:`~loopcal.simulator.clock.HeldClock` is released by the
        first request).
    wire : WireFaults
        The wire fault state.

    Attributes
    ----------
    device : LDQ412
        As given.
    clock : Clock
        As given.
    wire : WireFaults
        As given.
    lock : threading.RLock
        Serializes every access to the device and the wire.
    requested : threading.Event
        Set by the first request a server handles.
    links_boot : int
        The power-on the open TCP connections belong to: the emulator resets them when the
        module boots again, and a request on one of them before that is not answered.
    """

    def __init__(self, device: LDQ412, clock: Clock, wire: WireFaults) -> None:
        self.device = device
        self.clock = clock
        self.wire = wire
        self.lock = threading.RLock()
        self.requested = threading.Event()  # set by the first request a server handles
        # the power-on the open TCP connections belong to (the emulator resets them when
        # the module boots again; a request on one of them before that is not answered)
        self.links_boot = device.boot

    def note_request(self) -> None:
        """A server received a request: the first one sets :attr:`requested` and starts a
        clock held until then (:class:`~loopcal.simulator.clock.HeldClock`)."""
        if not self.requested.is_set():
            if isinstance(self.clock, HeldClock):
                self.clock.release()
            self.requested.set()

    @contextmanager
    def synced(self) -> Iterator[LDQ412]:
        """Hold the lock with the device synced to the clock's current time.

        Yields
        ------
        LDQ412
            The device, synced (:meth:`~loopcal.simulator.device.LDQ412.sync`), for the
            ``with`` block's duration, under the lock.
        """
        with self.lock:
            self.device.sync(self.clock.now_ns())
            yield self.device

    def responsive_locked(self) -> bool:
        """Whether the module would answer now: ready, not stalled, link up.

        Call it holding :attr:`lock`, after a sync (inside :meth:`synced`).

        Returns
        -------
        bool
            Powered and past its first scan, not stalled, and the link not cut.
        """
        return (
            self.device.ready
            and not self.wire.disconnected
            and not self.wire.stalled(self.device.now_ns)
        )
