"""Which scans a recording file lost, from what the file itself holds.

A scan is identified within a file by its power-on epoch and counter. The raw scans
(``/daq/scans``) are the record; the per-scan views (``/joint/state``, one message per scan,
in a chunk of their own after the raw one) carry each scan's epoch, counter and stamp too, so
a scan whose raw chunk was lost but whose view was kept is known to be missing, counter and
all, even at the very start or end of a file where no counter gap shows it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cdr import JOINT_STATE_DTYPE
from .schemas import CDR_LE, NS_PER_S

#: fields of a scan's key, as :func:`view_keys` returns them
KEY_DTYPE = np.dtype([("epoch", "<u4"), ("counter64", "<u8"), ("stamp_ns", "<i8")])
#: a whole ``/joint/state`` message: the CDR encapsulation header, then the fields
_VIEW = np.dtype({
    "names": ["sec", "nanosec", "epoch", "counter"],
    "formats": [JOINT_STATE_DTYPE.fields[f][0] for f in ("sec", "nanosec", "epoch", "counter")],
    "offsets": [len(CDR_LE) + JOINT_STATE_DTYPE.fields[f][1]
                for f in ("sec", "nanosec", "epoch", "counter")],
    "itemsize": len(CDR_LE) + JOINT_STATE_DTYPE.itemsize,
})  # fmt: skip


@dataclass(frozen=True)
class Loss:
    """Scans a file should hold and does not (a damaged or missing chunk).

    A counter gap between two of its scans that no recorded ``missed`` count explains, or
    scans whose views the file holds but whose raw scans it does not.

    Attributes
    ----------
    epoch : int
        The power-on epoch of the scans.
    first : int
        ``counter64`` of the first missing scan.
    count : int
        How many scans are missing, >= 1.
    after_ns : int
        Stamp of the scan before them, ns since the Unix epoch (the first missing scan's
        own stamp when no scan of the file comes before).
    before_ns : int
        Stamp of the scan after them (the last missing scan's own stamp when no scan of
        the file comes after).
    """

    epoch: int
    first: int
    count: int
    after_ns: int
    before_ns: int


def view_keys(messages: list[bytes]) -> np.ndarray:
    """The keys (:data:`KEY_DTYPE`) of the scans ``/joint/state`` messages describe.

    Parameters
    ----------
    messages : list of bytes
        ``/joint/state`` messages (CDR); any of another length or encoding is skipped.

    Returns
    -------
    ndarray of KEY_DTYPE, shape (n,)
        Epoch, counter and stamp of each well-formed message, in the order given.
    """
    if not all(len(m) == _VIEW.itemsize and m[:4] == CDR_LE for m in messages):
        messages = [m for m in messages if len(m) == _VIEW.itemsize and m[:4] == CDR_LE]
    arr = np.frombuffer(b"".join(messages), dtype=_VIEW)
    keys = np.zeros(len(arr), dtype=KEY_DTYPE)
    keys["epoch"], keys["counter64"] = arr["epoch"], arr["counter"]
    keys["stamp_ns"] = arr["sec"].astype(np.int64) * NS_PER_S + arr["nanosec"]
    return keys


def _union(
    rows: np.ndarray, seen: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Epoch, counter, stamp, missed and "read" of the scans of ``rows`` and of ``seen``
    (keys only: missed 0, not read), each key once and in (epoch, counter) order."""
    n, m = len(rows), len(seen)
    if not m:  # rows alone are in order already, each key once
        return rows["epoch"], rows["counter64"], rows["stamp_ns"], rows["missed"], np.ones(n, bool)
    e = np.concatenate([rows["epoch"], seen["epoch"]])
    c = np.concatenate([rows["counter64"], seen["counter64"]])
    s = np.concatenate([rows["stamp_ns"], seen["stamp_ns"]])
    missed = np.concatenate([rows["missed"], np.zeros(m, dtype=rows["missed"].dtype)])
    read = np.concatenate([np.ones(n, dtype=bool), np.zeros(m, dtype=bool)])
    order = np.lexsort((~read, c, e))  # a key read and seen: the read one first
    e, c, s, missed, read = e[order], c[order], s[order], missed[order], read[order]
    keep = np.ones(n + m, dtype=bool)
    keep[1:] = (e[1:] != e[:-1]) | (c[1:] != c[:-1])
    return e[keep], c[keep], s[keep], missed[keep], read[keep]


def losses(rows: np.ndarray, seen: np.ndarray | None = None) -> list[Loss]:
    """The scans missing from ``rows``, as runs of consecutive counters.

    Parameters
    ----------
    rows : ndarray of SCAN_DTYPE
        The scans read, in (epoch, counter) order, each once.
    seen : ndarray of KEY_DTYPE, optional
        Keys of scans the file describes otherwise (its views); those not in ``rows`` are
        missing.

    Returns
    -------
    list of Loss
        Counter gaps that the ``missed`` counts do not explain (within an epoch,
        ``counter - previous - 1 > missed``; at a new epoch's first scan in the file,
        ``counter > missed``), and the scans of ``seen`` that ``rows`` lacks, adjacent
        ones merged, in (epoch, counter) order.
    """
    if seen is None:
        seen = np.zeros(0, dtype=KEY_DTYPE)
    e, c, s, m, read = _union(rows, seen)
    if len(e) == 0:
        return []
    same = e[1:] == e[:-1]
    m64 = m.astype(np.uint64)
    step = np.where(same, c[1:] - c[:-1] - np.uint64(1), c[1:])
    gap = np.zeros(len(e), dtype=np.uint64)
    gap[1:] = np.where(step > m64[1:], step - m64[1:], np.uint64(0))
    runs: list[list[int]] = []  # [epoch, first, count, after_ns, before_ns]

    def add(epoch: int, first: int, count: int, after: int, before: int) -> None:
        last = runs[-1] if runs else None
        if last is not None and last[0] == epoch and last[1] + last[2] == first:
            last[2] += count
            last[4] = before
        else:
            runs.append([epoch, first, count, after, before])

    n = len(e)
    for i in np.flatnonzero((gap > 0) | ~read):
        if gap[i]:
            first = int(c[i - 1]) + 1 if same[i - 1] else int(m[i])
            add(int(e[i]), first, int(gap[i]), int(s[i - 1]), int(s[i]))
        if not read[i]:
            add(int(e[i]), int(c[i]), 1, int(s[i - 1] if i else s[i]),
                int(s[i + 1] if i + 1 < n else s[i]))  # fmt: skip
    return [Loss(*run) for run in runs]


def losses_within(
    rows: np.ndarray, since: int | None, until: int | None, seen: np.ndarray | None = None
) -> list[Loss]:
    """The losses of ``rows`` (:func:`losses`) between two scans both stamped in
    ``since <= stamp < until``."""

    def inside(ns: int) -> bool:
        return (since is None or ns >= since) and (until is None or ns < until)

    return [x for x in losses(rows, seen) if inside(x.after_ns) and inside(x.before_ns)]


__all__ = ["KEY_DTYPE", "Loss", "losses", "losses_within", "view_keys"]
