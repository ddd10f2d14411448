"""Device time -> UTC for one power-on of the module: the recorder's time stamps.

A scan's device time counts the module's own µs; the host knows only when answers arrive.
Every answer gives a sample ``arrival - device time`` (UTC ns minus device ns): the offset
between the two clocks plus how old the scan was when its answer arrived. Ages are never
negative and the smallest over many reads is close to zero, so the offset is the samples'
lower envelope. The module's clock is not the host's (the datasheet does not say how good
it is: ±200 ppm moves the offset by 0.7 s an hour; an emulated module at ``--speed 10``
runs ten times as fast), so the envelope is a sloping line:

- the lowest sample in each 10 s of device time (a bin), once the slope is taken out, is
  close to the envelope;
- the slope (the module's clock rate against the host's, less 1) is the least-squares slope
  of the last ten minutes of bin minima, once they span half a minute. Before that it is
  0, unless the slope from the first sample to the newest is beyond ±5 % and has moved the
  samples by more than 1.5 s (more than any scan's age, a period at 1 Hz and the answer
  time): no crystal is that far off, but an emulator at ``--speed 10`` is (-90 %), and
  would be followed only after half a minute of its device time. The fitted slope is held
  within ±1000 ppm (what a crystal can be off, and the fit's noise with it), or, once the
  first samples have shown a clock beyond any crystal, only to one that runs forward;
- the line goes through the lowest of the last minute's samples once the slope is taken
  out of them (a sample of little age), so it neither lags a fast clock nor runs ahead of a
  slow one the way a plain minimum over the minute did (by up to 12 ms at 200 ppm);
- the host's clock being set is told by the host's own two clocks, UTC against monotonic
  (both passed to :meth:`ClockMap.observe`), not by the samples: when that difference
  steps by more than 0.5 s, everything the map learnt moves with it.

The stamps: the line, then a floor, the rule that keeps them in order whatever the line
learns: each stamp is at least 1 ns after the stamp before it (within a map, and across
power-ons: a map for a new one starts from the last map's :class:`StampFloor`), so stamps
strictly increase with the counter. What it costs: a refit that lowers the line by x holds
the next scans at the floor until the line passes it again, stamped up to x late and 1 ns
apart. With a module within ±1000 ppm a refit moves the line by a few ms, less than a
scan period: over 6 simulated hours (bench/bench_stamps.py) the floor raised no stamp at
all. An emulator at another speed is followed after its first read or two (until the
samples have moved 1.5 s), and the floor holds some scans of those reads. The scans that
waited in the FIFO before the first read are stamped at the nominal rate back from it (at
``--speed 10`` up to 12.8 s back, where they took 1.28 s): no map knows the rate yet.

The one exception is the host's clock being set back: the floor moves back with it, and
the stamps step back by as much. The recorder starts a new file there, so that within a
file stamps never go back (:mod:`loopcal.daemon.recorder.filewriter`).
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

BIN_US = 10_000_000  # device µs per bin of the lower envelope
SLOPE_BINS = 60  # bins the slope is fitted over (10 minutes)
OFFSET_BINS = 6  # bins whose minima can set the line's height (1 minute)
SLOPE_MIN_SPAN_US = 30_000_000  # the slope is fitted once the bins span this
EARLY_SLOPE = 0.05  # before that, a slope this far from 0 (no crystal's: an emulator's)
EARLY_DRIFT_NS = 1_500_000_000  # that moved the samples more than a scan's age can (1 Hz)
SLOPE_LIMIT = 1e-3  # a crystal's slope is held within this (the fit's noise with it)
SLOPE_MIN = -0.999  # any other clock's: at most 1000 times as fast as the host's
SLOPE_MAX = 999.0  # and at most 1000 times as slow
CLOCK_STEP_NS = 500_000_000  # UTC - monotonic moved this much at once: the host clock was set
_NO_STAMP = -(1 << 62)


@dataclass(frozen=True)
class StampFloor:
    """The last stamp handed on (UTC ns) and the host's UTC - monotonic (ns) when it was:
    later stamps come after it, moved by any step of the host's clock since."""

    stamp_ns: int
    host_offset_ns: int


class ClockMap:
    """Device time -> UTC (ns) for one power-on epoch, from the arrivals of its scans.

    after: the floor to start from (the previous power-on's map's :attr:`floor`), so that
    this map's stamps come after every stamp already handed on.
    """

    def __init__(self, after: StampFloor | None = None) -> None:
        # per bin: (bin index, device µs of its lowest sample, that sample in ns)
        self._bins: collections.deque[tuple[int, int, int]] = collections.deque(
            maxlen=SLOPE_BINS
        )
        self.slope = 0.0  # UTC ns per device ns, minus 1: -2e-4 for a module 200 ppm fast
        self.crystal = True  # the slope is a crystal's (False: an emulator at another speed)
        self.offset_ns: int | None = None  # the line at device time 0
        self._base = 0  # samples are fitted relative to this (float64 keeps ns precision)
        self._first: tuple[int, int] | None = None  # (device µs, sample ns) of the first
        self._last_stamp = after.stamp_ns if after is not None else _NO_STAMP
        #: the host's UTC - monotonic, ns, at the latest answer (None before the first)
        self._host_offset = after.host_offset_ns if after is not None else None
        self.host_steps = 0  # how often the host's clock was seen to be set

    @property
    def floor(self) -> StampFloor | None:
        """Where a map of the next power-on starts from (None before any answer)."""
        if self._host_offset is None:
            return None
        return StampFloor(self._last_stamp, self._host_offset)

    def observe(self, mono_s: float, arrival_ns: int, time64_us: int) -> None:
        """One answer: its arrival (UTC ns, and mono_s, the same instant by the host's
        monotonic clock, s) and the device time of the newest scan it carried."""
        host_offset = arrival_ns - round(mono_s * 1e9)
        if self._host_offset is not None and abs(host_offset - self._host_offset) > CLOCK_STEP_NS:
            self._host_clock_set(host_offset - self._host_offset)
        self._host_offset = host_offset
        sample = arrival_ns - time64_us * 1000
        if not self._bins:
            self._base = sample
        if self._first is None:
            self._first = (time64_us, sample)
        changed = self._update_bins(time64_us, sample)
        if not self._fitted:
            early = self._early_slope(time64_us, sample)
            changed = changed or early != self.slope
            self.slope = early
        if changed:  # the line is a function of the bins and the slope
            self._refit()

    def _update_bins(self, time64_us: int, sample: int) -> bool:
        """Whether the sample changed the bins: a bin keeps its lowest sample once the slope
        is taken out; an older bin than the newest is left (its scans are stamped)."""
        k = time64_us // BIN_US
        bins = self._bins
        if bins and bins[-1][0] == k:
            old_t, old = bins[-1][1], bins[-1][2]
            if not sample - old < self.slope * (time64_us - old_t) * 1000:
                return False
            bins[-1] = (k, time64_us, sample)
            return True
        if not bins or k > bins[-1][0]:
            bins.append((k, time64_us, sample))
            return True
        return False

    @property
    def _fitted(self) -> bool:
        """Whether the bins span enough for the slope to be fitted to them."""
        b = self._bins
        return len(b) >= 3 and b[-1][1] - b[0][1] >= SLOPE_MIN_SPAN_US

    def _early_slope(self, time64_us: int, sample: int) -> float:
        """Before the fit: the slope from the first sample to this one if it is beyond ±5 %
        and has moved the sample by more than any scan's age could (1.5 s); else 0."""
        assert self._first is not None
        t0, y0 = self._first
        drift = sample - y0
        if time64_us <= t0 or abs(drift) < EARLY_DRIFT_NS:
            return 0.0
        early = drift / ((time64_us - t0) * 1000)
        if abs(early) < EARLY_SLOPE:
            return 0.0
        self.crystal = False
        return max(SLOPE_MIN, min(SLOPE_MAX, early))

    def _host_clock_set(self, step_ns: int) -> None:
        """The host's clock was set by ``step_ns``: the samples so far, the line and the
        floor move with it (the module's clock did not change)."""
        self._bins = collections.deque(
            ((k, t, s + step_ns) for k, t, s in self._bins), maxlen=SLOPE_BINS
        )
        self._base += step_ns
        if self._first is not None:
            self._first = (self._first[0], self._first[1] + step_ns)
        if self.offset_ns is not None:
            self.offset_ns += step_ns
        if self._last_stamp != _NO_STAMP:
            self._last_stamp += step_ns
        self.host_steps += 1

    def _refit(self) -> None:
        bins = self._bins
        t = np.array([b[1] for b in bins], dtype=np.float64) * 1000  # device ns
        y = np.array([b[2] - self._base for b in bins], dtype=np.float64)
        if self._fitted:
            tc = t - t.mean()
            slope = float((tc * (y - y.mean())).sum() / (tc * tc).sum())
            lo, hi = (-SLOPE_LIMIT, SLOPE_LIMIT) if self.crystal else (SLOPE_MIN, SLOPE_MAX)
            self.slope = max(lo, min(hi, slope))
        recent = slice(-OFFSET_BINS, None)
        self.offset_ns = self._base + round(float(np.min(y[recent] - self.slope * t[recent])))

    def line_stamps(self, time64_us: np.ndarray) -> np.ndarray:
        """The line itself at these device times, ns (what :meth:`stamps` gives before the
        floor; for measuring what the floor costs)."""
        assert self.offset_ns is not None
        t = time64_us.astype(np.int64)
        return t * 1000 + self.offset_ns + np.round(self.slope * t * 1000).astype(np.int64)

    def stamps(self, time64_us: np.ndarray) -> np.ndarray:
        """UTC stamps, ns, of scans newer than any stamped so far (oldest first): the line,
        each at least 1 ns after the stamp before it."""
        s = self.line_stamps(time64_us)
        if not len(s):
            return s
        # s'[i] = max(s[i], s'[i-1] + 1, last + 1): a running maximum of s[i] - i
        i = np.arange(len(s), dtype=np.int64)
        s = np.maximum.accumulate(np.maximum(s - i, self._last_stamp + 1)) + i
        self._last_stamp = int(s[-1])
        return s
