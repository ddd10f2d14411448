"""Device time -> UTC for one power-on of the module: the recorder's time stamps.

A scan's device time counts the module's own µs; the host knows only when answers arrive.
Every answer gives a sample ``arrival - device time`` (UTC ns minus device ns): the offset
between the two clocks plus how old the scan was when its answer arrived. Ages are never
negative and the smallest over many reads is close to zero, so the offset is the samples'
lower envelope. The module's clock is not the host's (the datasheet does not say how good
it is: ±200 ppm moves the offset by 0.7 s an hour), so the envelope is a sloping line:

- the lowest sample in each 10 s of device time (a bin), once the slope is taken out, is
  close to the envelope;
- the slope (the module's clock error) is the least-squares slope of the last ten minutes
  of bin minima, once they span half a minute (0 before), held within ±1000 ppm;
- the line goes through the lowest of the last minute's samples once the slope is taken
  out of them (a sample of little age), so it neither lags a fast clock nor runs ahead of a
  slow one the way a plain minimum over the minute did (by up to 12 ms at 200 ppm);
- a sample more than 0.5 s off the line means the host's clock was set: start over.

Stamps strictly increase within the power-on.
"""

from __future__ import annotations

import collections

import numpy as np

BIN_US = 10_000_000  # device µs per bin of the lower envelope
SLOPE_BINS = 60  # bins the slope is fitted over (10 minutes)
OFFSET_BINS = 6  # bins whose minima can set the line's height (1 minute)
SLOPE_MIN_SPAN_US = 30_000_000  # the slope is 0 until the bins span this
SLOPE_LIMIT = 1e-3
CLOCK_STEP_NS = 500_000_000  # a sample this far off the line: the host clock was set


class ClockMap:
    """Device time -> UTC (ns) for one power-on epoch, from the arrivals of its scans."""

    def __init__(self) -> None:
        # per bin: (bin index, device µs of its lowest sample, that sample in ns)
        self._bins: collections.deque[tuple[int, int, int]] = collections.deque(
            maxlen=SLOPE_BINS
        )
        self.slope = 0.0  # UTC ns per device ns, minus 1: -2e-4 for a module 200 ppm fast
        self.offset_ns: int | None = None  # the line at device time 0
        self._base = 0  # samples are fitted relative to this (float64 keeps ns precision)
        self._last_stamp = -(1 << 62)

    def _line(self, time64_us: int) -> float:
        assert self.offset_ns is not None
        return self.offset_ns + self.slope * time64_us * 1000

    def observe(self, mono_s: float, arrival_ns: int, time64_us: int) -> None:
        """One answer: its arrival (UTC ns; mono_s, the host's monotonic s, is not needed
        but kept for callers) and the device time of the newest scan it carried."""
        del mono_s
        sample = arrival_ns - time64_us * 1000
        if self.offset_ns is not None and abs(sample - self._line(time64_us)) > CLOCK_STEP_NS:
            self._bins.clear()
            self.slope = 0.0
            self._last_stamp = -(1 << 62)
        if not self._bins:
            self._base = sample
        k = time64_us // BIN_US
        bins = self._bins
        if bins and bins[-1][0] == k:
            # the bin keeps its lowest sample once the slope is taken out
            old_t, old = bins[-1][1], bins[-1][2]
            if not sample - old < self.slope * (time64_us - old_t) * 1000:
                return  # not lower: the bins, so the line, are as they were
            bins[-1] = (k, time64_us, sample)
        elif not bins or k > bins[-1][0]:
            bins.append((k, time64_us, sample))
        else:  # an older bin than the newest: its scans are already stamped
            return
        self._refit()  # only when the bins changed: the line is a function of them

    def _refit(self) -> None:
        bins = self._bins
        t = np.array([b[1] for b in bins], dtype=np.float64) * 1000  # device ns
        y = np.array([b[2] - self._base for b in bins], dtype=np.float64)
        if len(bins) >= 3 and t[-1] - t[0] >= SLOPE_MIN_SPAN_US * 1000:
            tc = t - t.mean()
            slope = float((tc * (y - y.mean())).sum() / (tc * tc).sum())
            self.slope = max(-SLOPE_LIMIT, min(SLOPE_LIMIT, slope))
        recent = slice(-OFFSET_BINS, None)
        self.offset_ns = self._base + round(float(np.min(y[recent] - self.slope * t[recent])))

    def stamps(self, time64_us: np.ndarray) -> np.ndarray:
        """UTC stamps, ns, strictly increasing within the epoch."""
        assert self.offset_ns is not None
        t = time64_us.astype(np.int64)
        s = t * 1000 + self.offset_ns + np.round(self.slope * t * 1000).astype(np.int64)
        s = np.maximum(s, self._last_stamp + 1 + np.arange(len(s)))
        if len(s):
            self._last_stamp = int(s[-1])
        return s
