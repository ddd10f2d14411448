"""Process-wide setup for the long-running commands: logging and signals.

Logging goes to stderr: under systemd (``JOURNAL_STREAM`` set) without time stamps, since
the journal adds its own, with a syslog priority prefix so ``journalctl -p warning`` works;
in a terminal with time stamps. pymodbus logs an ERROR line for every ordinary timeout;
those are silenced here, and the acquisition reports link trouble as its own events.
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
from collections.abc import Callable

from .engine import Recorder

_SYSLOG_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3,
                    logging.CRITICAL: 2}  # fmt: skip


class _JournalFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        prio = _SYSLOG_PRIORITY.get(record.levelno, 6)
        return f"<{prio}>{super().format(record)}"


def setup_logging(verbose: bool = False) -> None:
    """Log to stderr, in the journal's format under systemd."""
    handler = logging.StreamHandler(sys.stderr)
    if os.environ.get("JOURNAL_STREAM"):
        handler.setFormatter(_JournalFormatter("%(levelname)s %(name)s: %(message)s"))
    else:
        handler.setFormatter(
            logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
        )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    # pymodbus logs every timeout at ERROR; the acquisition reports outages itself.
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL + 1)


def run_recorder(recorder: Recorder) -> int:
    """Run a recorder in this (main) thread until SIGTERM or SIGINT; SIGHUP reloads.

    A file-size limit (RLIMIT_FSIZE) must give an error the recorder can handle, not kill
    the process, so SIGXFSZ is ignored.
    """
    if threading.current_thread() is threading.main_thread():
        for sig, handler in signal_handlers(recorder).items():
            signal.signal(sig, handler)
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    return recorder.run()


def signal_handlers(recorder: Recorder) -> dict[signal.Signals, Callable[[int, object], None]]:
    """SIGTERM and SIGINT stop the recorder, SIGHUP reloads it: each handler only notes the
    signal, taking no lock (:meth:`Recorder.signal_stop`)."""
    return {
        signal.SIGTERM: lambda *_: recorder.signal_stop("SIGTERM"),
        signal.SIGINT: lambda *_: recorder.signal_stop("SIGINT"),
        signal.SIGHUP: lambda *_: recorder.signal_reload(),
    }
