"""Real things at an address that are not the module's own: a bare serial line (a
null-modem pty link) for the tests of the line itself."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from loopcal.simulator.pty import PtyLink


@contextmanager
def running_link(baud: int) -> Iterator[PtyLink]:
    """A bare null-modem pty link (:class:`~loopcal.simulator.pty.PtyLink`) whose module
    side is at ``baud``, relaying on a loop of its own; closed after."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    link = PtyLink(baud)
    started = threading.Event()
    loop.call_soon_threadsafe(lambda: (link.start(loop, lambda: True), started.set()))
    assert started.wait(5)
    try:
        yield link
    finally:
        done = threading.Event()
        loop.call_soon_threadsafe(lambda: (link.close(), done.set()))
        done.wait(5)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(5)
        loop.close()
