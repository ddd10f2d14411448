"""Scans as the daemon keeps them: one row of a numpy structured array per scan.

The driver hands over :class:`loopcal.drivers.Scan` records; the acquisition turns every batch of
them into rows of :data:`SCAN_DTYPE` (adding the recorder's power-on epoch and UTC time
stamps), the recorder writes those rows to MCAP unchanged, and the reader gives the same
rows back. A row keeps everything the module said, losslessly: the raw 32-bit counter and
device time are the low 32 bits of ``counter64`` and ``time64_us``.

The field order puts 8-byte fields first, so the numpy layout (``align=True``) has no
padding between fields and is also the CDR layout of the ``loopcal_msgs/Scan`` message
the recording stores (see :mod:`loopcal.daemon.recording`).
"""

from __future__ import annotations

import numpy as np

from loopcal.drivers import ldq412

#: (name, numpy scalar type, count, meaning): the fields of a scan row, in layout order
SCAN_FIELDS: tuple[tuple[str, str, int, str], ...] = (
    ("counter64", "uint64", 1, "scans since the module's power-on (the 32-bit counter, unwrapped)"),
    ("time64_us", "uint64", 1, "device time of channel 1's conversion since power-on, us"),
    ("stamp_ns", "int64", 1, "estimated acquisition time, ns since the Unix epoch (UTC)"),
    ("host_ns", "int64", 1, "when the host received the scan, ns since the Unix epoch (UTC)"),
    ("epoch", "uint32", 1, "power-on epoch of the module as recorded: +1 at each restart"),
    ("missed", "uint32", 1, "scans made just before this one that were never received"),
    ("codes", "uint16", 4, "channel 1..4 ADC codes, 0..4095"),
    ("status", "uint16", 1, "status: bits 0-3 rail, 4-7 sensor fault, 8 overflow, 9 restart"),
    ("restarted", "bool", 1, "the module restarted (power cycle) just before this scan"),
    ("overflow", "bool", 1, "the module's FIFO overflowed just before this scan"),
    ("time_measured", "bool", 1, "time64_us read from the module (else derived from the rate)"),
    ("status_measured", "bool", 1, "status read from the module for this very scan"),
    ("from_fifo", "bool", 1, "delivered from the FIFO (else by polling the latest scan)"),
)

SCAN_DTYPE = np.dtype(
    [(name, kind, (count,)) if count > 1 else (name, kind) for name, kind, count, _ in SCAN_FIELDS],
    align=True,
)


def empty(n: int = 0) -> np.ndarray:
    """n zeroed scan rows."""
    return np.zeros(n, dtype=SCAN_DTYPE)


def volts(scans: np.ndarray) -> np.ndarray:
    """Channel voltages by the datasheet's mid-code reconstruction, V, shape (n, 4)."""
    return ldq412.code_to_volts(scans["codes"])


def rail(scans: np.ndarray) -> np.ndarray:
    """(n, 4) bool: channel at the rail (status bits 0-3, or a code of 0 or 4095)."""
    return _bits(scans["status"], 0) | ldq412.at_rail(scans["codes"])


def fault(scans: np.ndarray) -> np.ndarray:
    """(n, 4) bool: sensor fault on the channel (status bits 4-7)."""
    return _bits(scans["status"], 4)


def trustworthy(scans: np.ndarray) -> np.ndarray:
    """(n, 4) bool: neither at the rail nor faulted (the datasheet's trustworthy reading)."""
    return ~(rail(scans) | fault(scans))


def _bits(status: np.ndarray, shift: int) -> np.ndarray:
    s = np.asarray(status, dtype=np.uint16)[:, None]
    return ((s >> (shift + np.arange(4, dtype=np.uint16))) & 1).astype(bool)


def scan_rate_hz(scans: np.ndarray) -> float:
    """The scan rate of scan rows, Hz, from the device times of consecutive scans (the
    median period within a power-on epoch); 20 Hz, the datasheet's default, when fewer
    than two consecutive scans say otherwise."""
    if len(scans) < 2:
        return float(ldq412.SCAN_RATE_DEFAULT_HZ)
    same = (np.diff(scans["epoch"]) == 0) & (np.diff(scans["counter64"].astype(np.int64)) == 1)
    dt = np.diff(scans["time64_us"].astype(np.int64))[same]
    return 1e6 / float(np.median(dt)) if len(dt) else float(ldq412.SCAN_RATE_DEFAULT_HZ)
