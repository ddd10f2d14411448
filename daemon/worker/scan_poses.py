"""MCAP -> scans for the fit: every usable scan of a recording, moving or still.

The maximum-likelihood fit takes each scan as a pose of its own (one unknown plate rotation
per scan), so the whole of a technician's hand motion counts, not only the pauses
(docs/calibration.md). Before that, as for still poses
(:mod:`loopcal.daemon.worker.recorded_poses`):

- scans with a channel at the rail or faulted, and scans within ``gap_margin_s`` of a gap or
  restart, are left out;
- each remaining scan's readings are brought to its own time stamp
  (:func:`loopcal.calibration.scans.deskew`: channel i is converted i x 250 µs after the
  stamp), the rate taken from its neighbours; a scan with no usable neighbour is left out;
- the sensor noise of one reading comes from fourth differences, which a hand's motion does
  not inflate (:func:`loopcal.calibration.scans.difference_noise`).

A recording with more usable scans than :data:`MAX_FIT_SCANS` (a day holds 1.7 million) is
thinned to an even stride over its whole span (bench/bench_scans.py states what that costs
in precision). Held-out stretches for the holdout gate are whole blocks of
:data:`HOLDOUT_BLOCK_S` of time (every
:data:`~loopcal.daemon.worker.gates.residual.HOLDOUT_EVERY`-th),
so that the check is on motion the fit did not see, not on the neighbours of fitted scans.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from loopcal.calibration.scans import CHANNEL_SKEW_S, deskew, difference_noise

from .gates.residual import HOLDOUT_BLOCK_S
from .recorded_poses import GAP_MARGIN_S, RecordedPoses, screen_scans

#: at most this many scans go into one fit (10 minutes at 20 Hz)
MAX_FIT_SCANS = 12_000


@dataclass(frozen=True)
class RecordedScans(RecordedPoses):
    """Usable scans of a recording as single-scan poses (counts all 1; ``rows[k]`` is
    ``(row, row + 1)``; ``volts`` deskewed; ``scan_noise`` each channel's noise from fourth
    differences, the same in every row).

    block: (k,) index of the block of :data:`HOLDOUT_BLOCK_S` worth of scans (at the scan
    rate) each scan falls in, counted from the recording's first scan. usable: scans that
    passed the screening before thinning. stride: the thinning (1: every usable scan).
    """

    block: np.ndarray = None  # type: ignore[assignment]
    usable: int = 0
    stride: int = 1

    @property
    def seconds(self) -> float:
        """The usable scans' time at the scan rate, s (before thinning)."""
        return self.usable / self.scan_rate_hz if self.scan_rate_hz > 0 else 0.0


def scans_for_fit(
    s: np.ndarray,
    *,
    gap_margin_s: float = GAP_MARGIN_S,
    max_scans: int = MAX_FIT_SCANS,
    skew_s: float = CHANNEL_SKEW_S,
) -> RecordedScans:
    """The usable scans of scan rows (SCAN_DTYPE, oldest first; the module docstring).

    gap_margin_s: scans this close to a gap or restart are left out. max_scans: more usable
    scans than this are thinned to an even stride. skew_s: the delay between two channels'
    conversions the readings are corrected for, s (0: not corrected, for comparison).
    """
    volts, valid, dropped, rate = screen_scans(s, gap_margin_s=gap_margin_s)
    neighbour = np.zeros_like(valid)
    neighbour[1:] |= valid[:-1]
    neighbour[:-1] |= valid[1:]
    dropped["no usable neighbour to correct its channel skew"] = int((valid & ~neighbour).sum())
    rows = np.flatnonzero(valid & neighbour)
    usable = len(rows)
    stride = max(1, -(-usable // max_scans))
    if stride > 1:  # before the correction: a day's scans are never all converted
        kept = rows[::stride]
        dropped[f"thinned to every {stride}th usable scan"] = usable - len(kept)
        rows = kept
    period = 1.0 / rate if rate > 0 else 0.05
    V, _ = deskew(volts, period, valid=valid, rows=rows, skew_s=skew_s)
    noise = difference_noise(volts, valid=valid, rows=rows)
    noise = np.where(np.isfinite(noise), noise, 0.0)
    idx = rows
    stamps = s["stamp_ns"][idx]
    k = len(idx)
    # blocks by scan count at the scan rate, not by stamps: an accelerated replay or
    # emulator packs its stamps closer than the scans' own time
    per_block = max(1, round(HOLDOUT_BLOCK_S * rate)) if rate > 0 else 100
    return RecordedScans(
        volts=V,
        spread=np.zeros((k, 4)),
        scan_noise=np.broadcast_to(noise, (k, 4)),
        counts=np.ones(k, dtype=np.int64),
        rows=np.stack([idx, idx + 1], axis=1) if k else np.zeros((0, 2), dtype=np.int64),
        stamp_ns=stamps,
        scan_rate_hz=rate,
        dropped=dropped,
        block=(idx // per_block).astype(np.int64),
        usable=usable,
        stride=stride,
    )
