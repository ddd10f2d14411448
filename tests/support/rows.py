"""Scan rows (``loopcal.daemon.scan_rows.SCAN_DTYPE``) as the recorder makes them, built from
device times and codes: one builder (:func:`rows_from`), and the few sets of rows the tests
and bench scripts share.

Every stamp is ns since the Unix epoch, every device time µs of the module's own clock.
"""

from __future__ import annotations

import numpy as np

from loopcal.calibration.simulate import simulate_poses
from loopcal.daemon import scan_rows as S
from loopcal.drivers.ldq412 import volts_to_code

from .plate import held_and_moved

#: the first scan's stamp of the tests' recordings, ns since the Unix epoch (late 2026)
T0 = 1_795_000_000_000_000_000
#: one past the largest 32-bit counter or device time
U32 = 1 << 32
#: what the host's stamp of a scan trails its device time by, ns (a read's latency)
HOST_DELAY_NS = 2_000_000


def rows_from(
    time_us: np.ndarray,
    codes: np.ndarray,
    *,
    counter: np.ndarray | None = None,
    t0: int = T0,
    epoch: int = 0,
) -> np.ndarray:
    """Scan rows of one power-on, as the recorder makes them from the module's FIFO.

    Parameters
    ----------
    time_us : ndarray of int, shape (n,)
        Each scan's device time, µs.
    codes : ndarray of int, shape (n, 4)
        Each scan's four 12-bit codes.
    counter : ndarray of int, shape (n,), optional
        Each scan's 64-bit counter (default 0, 1, ..., n - 1).
    t0 : int
        The stamp of device time 0, ns since the Unix epoch: ``stamp_ns = t0 + time_us *
        1000``.
    epoch : int
        The recorder's power-on epoch of every row.

    Returns
    -------
    ndarray of SCAN_DTYPE, shape (n,)
        With the rail bits of the status set where a code is 0 or 4095.
    """
    time_us = np.asarray(time_us, dtype=np.int64)
    codes = np.asarray(codes)
    rows = S.empty(len(time_us))
    rows["counter64"] = np.arange(len(time_us)) if counter is None else counter
    rows["time64_us"] = time_us
    rows["stamp_ns"] = t0 + time_us * 1000
    rows["host_ns"] = rows["stamp_ns"] + HOST_DELAY_NS
    rows["epoch"] = epoch
    rows["codes"] = codes
    rail = (codes == 0) | (codes == 4095)
    rows["status"] = (rail * (1 << np.arange(4))).sum(axis=1)
    rows["from_fifo"] = True
    return rows


def make_rows(n: int, *, start: int = 0, seed: int = 0, t0: int = T0, epoch: int = 3) -> np.ndarray:
    """``n`` consecutive scans of a 20 Hz module from counter ``start`` on (device time
    ``counter * 50 ms + 7 µs``, stamped ``t0 + counter * 50 ms``), the codes of
    simulated poses."""
    c = np.arange(start, start + n, dtype=np.int64)
    codes = volts_to_code(simulate_poses(max(n, 10), seed=seed).volts[:n])
    return rows_from(c * 50_000 + 7, codes, counter=c, t0=t0 - 7_000, epoch=epoch)


def _power_on(first: int, n: int, *, phase_us: int, rate: int, gaps: dict[int, int], seed: int):
    """Counters first.. (n scans, with ``gaps``: index -> scans skipped before it), device
    times ``phase + counter * period`` (the module's own µs), random but smooth codes."""
    skip = np.zeros(n, dtype=np.int64)
    for i, k in gaps.items():
        skip[i] = k
    counter = first + np.arange(n, dtype=np.int64) + np.cumsum(skip)
    time_us = phase_us + counter * (1_000_000 // rate)
    rng = np.random.default_rng(seed)
    codes = np.clip(2048 + np.cumsum(rng.integers(-40, 41, (n, 4)), axis=0), 1, 4094)
    return counter, time_us, codes, skip


def synthetic_rows(rate: int = 50) -> np.ndarray:
    """Three power-ons of an independent module, as a recorder would have recorded them:

    0. on for 71.6 min when the recording starts: the device time passes 2**32 µs in
       the middle; 1 scan missed; channel 2 at the rail for a while;
    1. a restart: scan 0 came 700 µs after power-on; 3 scans missed; the clock runs 200
       ppm slow (the host stamps drift); a sensor fault;
    2. a restart the recorder saw late (6.8 years of scans at 20 Hz never read): the
       counter passes 2**32 and the device time wraps; scan 0 came 1809 µs after
       power-on; 5 scans missed; the clock 200 ppm fast.

    Each restart's 32-bit counter goes back, as the ASCII protocol needs to see one (it
    cannot clear the restart flag).
    """
    period = 1_000_000 // rate
    parts = [
        (_power_on(U32 // period - 40, 80, phase_us=0, rate=rate, gaps={50: 1}, seed=3), 0.0),
        (_power_on(0, 60, phase_us=700, rate=rate, gaps={25: 3}, seed=2), -200e-6),
        (_power_on(U32 - 40, 80, phase_us=1809, rate=rate, gaps={30: 5}, seed=1), 200e-6),
    ]
    out, host0 = [], T0
    for epoch, ((counter, time_us, codes, skip), ppm) in enumerate(parts):
        rows = rows_from(time_us, codes, counter=counter, epoch=epoch + 3)  # a recorder that
        rows["missed"] = skip  # had seen restarts before
        rows["restarted"][0] = True
        if epoch:
            rows["missed"][0] = counter[0]
        elapsed = (time_us - time_us[0]) * 1000 / (1 + ppm)  # the host's ns
        rows["stamp_ns"] = host0 + elapsed.astype(np.int64) + time_us[0] * 1000
        rows["host_ns"] = rows["stamp_ns"] + 3_000_000
        out.append(rows)
        host0 = int(rows["stamp_ns"][-1]) + 500_000_000  # off for half a second
    rows = np.concatenate(out)
    rows["codes"][20:30, 1] = 4095  # channel 2 at the rail
    rows["codes"][100:106, 2] = 4095  # channel 3 sensor fault
    rows["status"] = 1 << 9  # the restart flag, as an ASCII recorder never clears it
    rail = (rows["codes"] == 0) | (rows["codes"] == 4095)
    rows["status"] |= (rail * (1 << np.arange(4))).sum(axis=1).astype(np.uint16)
    rows["status"][100:106] |= 1 << 6
    rows["time_measured"] = rows["status_measured"] = True
    return rows


# --- independent readings of scan rows, and synthetic recordings (the worker's tests) ----

#: one code of the 12-bit converter over its 20 V span, V
LSB = 20.0 / 4096


def readings(s):
    """The datasheet's mid-code reconstruction, V."""
    return (s["codes"].astype(float) + 0.5) * LSB - 10.0


def untrustworthy(s):
    """(n,) a channel at the rail or faulted."""
    status = s["status"].astype(np.int64)
    at_rail = ((status & 0x0F) != 0) | np.any((s["codes"] == 0) | (s["codes"] == 4095), axis=1)
    return at_rail | ((status & 0xF0) != 0)


def near_a_break(s, margin):
    """(n,) within ``margin`` scans of a break, row by row."""
    missed, restarted, epoch = (s[f].tolist() for f in ("missed", "restarted", "epoch"))
    near = np.zeros(len(s), dtype=bool)
    for b in range(len(s)):
        if missed[b] > 0 or restarted[b] or (b > 0 and epoch[b] != epoch[b - 1]):
            near[max(0, b - margin) : b + margin] = True
    return near


def synthetic_scans(rng, n, rate, *, gaps=0, restarts=0, power_cycles=0, bad=0):
    """n scan rows at ``rate`` Hz of a plate moved and held still in turn, with scans
    missed before ``gaps`` rows, ``restarts`` restarted rows, ``power_cycles`` changes of
    epoch and ``bad`` rows with a channel at the rail (by its code or its status bit) or
    faulted."""
    V = held_and_moved(rng, n, hold=(2, 60), move=(1, 12))
    s = S.empty(n)
    s["codes"] = np.clip(np.floor((V + 10) / LSB), 0, 4095)
    if n == 0:
        return s
    s["missed"][rng.integers(0, n, gaps)] = rng.integers(1, 40, gaps)
    s["restarted"][rng.integers(0, n, restarts)] = True
    cycle = np.zeros(n, dtype=np.uint32)
    cycle[rng.integers(1, max(n, 2), power_cycles) % n] = 1
    s["epoch"] = 7 + np.cumsum(cycle)
    rows, channel = rng.integers(0, n, bad), rng.integers(0, 4, bad)
    kind = rng.integers(0, 4, bad)
    s["codes"][rows[kind == 0], channel[kind == 0]] = 0
    s["codes"][rows[kind == 1], channel[kind == 1]] = 4095
    s["status"][rows[kind == 2]] |= (1 << channel[kind == 2]).astype(np.uint16)
    s["status"][rows[kind == 3]] |= (1 << (4 + channel[kind == 3])).astype(np.uint16)
    # counters from 0 at each restart, on by the missed scans at a gap; stamps on by as
    # many scan periods, and 2 s more across a restart
    period_us = 1_000_000 // rate
    step = 1 + s["missed"].astype(np.int64)
    fresh = np.zeros(n, dtype=bool)
    fresh[1:] = s["restarted"][1:] | (np.diff(s["epoch"]) != 0)
    inc = np.where(fresh, 0, step)
    inc[0] = 0
    total = np.cumsum(inc)
    start = np.maximum.accumulate(np.where(fresh, np.arange(n), 0))
    s["counter64"] = total - total[start]
    advance = step * period_us * 1000 + fresh * 2_000_000_000
    advance[0] = 0
    s["stamp_ns"] = T0 + np.cumsum(advance)
    s["time64_us"] = s["counter64"] * period_us
    return s
