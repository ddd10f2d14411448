"""The worker's usable scans (daemon/worker/scan_poses.py) against what its docstring says, each
part computed here independently, row by row, from the scan rows' fields:

- a scan is left out if a channel is at the rail or faulted, or it lies within the gap
  margin of a break (as for still poses, tests/daemon/worker/test_poses.py), or if neither
  of its neighbouring rows is usable (no rate to correct its skew from);
- every scan read is accounted for: used, or dropped for one named reason;
- channel i's reading is moved by ``-i * 250 µs`` times its rate between the usable
  neighbours (central where both are, one-sided where one is);
- the noise is the scaled median absolute fourth difference over five usable rows;
- more usable scans than ``max_scans`` are thinned to an even stride, counted as dropped.

On synthetic recordings hypothesis draws (gaps, restarts, power cycles, rail and fault
scans) at several scan rates.
"""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from loopcal.daemon.worker.scan_poses import scans_for_fit
from tests.support.fuzz import examples
from tests.support.rows import near_a_break, readings, synthetic_scans, untrustworthy

SKEW_S = 250e-6


def expected(s, rate, margin, max_scans):
    n = len(s)
    V = readings(s)
    ok = ~untrustworthy(s) & ~near_a_break(s, margin)
    rows, alone = [], 0
    for r in range(n):
        if not ok[r]:
            continue
        prev = r > 0 and ok[r - 1]
        nxt = r < n - 1 and ok[r + 1]
        if prev or nxt:
            rows.append(r)
        else:
            alone += 1
    usable = len(rows)
    stride = max(1, math.ceil(usable / max_scans))
    kept = rows[::stride]
    volts = np.empty((len(kept), 4))
    for j, r in enumerate(kept):
        a = r - 1 if r > 0 and ok[r - 1] else r
        b = r + 1 if r < n - 1 and ok[r + 1] else r
        for i in range(4):
            rate_i = (V[b, i] - V[a, i]) / ((b - a) / rate)
            volts[j, i] = V[r, i] - i * SKEW_S * rate_i
    d4 = [
        V[r - 2] - 4 * V[r - 1] + 6 * V[r] - 4 * V[r + 1] + V[r + 2]
        for r in kept
        if 2 <= r <= n - 3 and all(ok[r + k] for k in (-2, -1, 1, 2))
    ]
    noise = (np.median(np.abs(d4), axis=0) / (0.6744897501960817 * math.sqrt(70))
             if d4 else np.zeros(4))  # fmt: skip
    return kept, volts, noise, usable, stride, alone, ok


@st.composite
def recordings(draw):
    n = draw(st.integers(0, 900))
    rate = draw(st.sampled_from([10, 20, 50]))
    counts = {
        key: draw(st.integers(0, max(1, n // 40)))
        for key in ("gaps", "restarts", "power_cycles", "bad")
    }
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    return synthetic_scans(rng, n, rate, **counts), rate, draw(st.sampled_from([50, 300, 10**6]))


@settings(max_examples=examples(80), deadline=None, derandomize=True, database=None)
@given(recordings())
def test_usable_scans_are_what_the_docstring_says(recording):
    s, rate, max_scans = recording
    margin = max(1, round(0.25 * rate))
    got = scans_for_fit(s, max_scans=max_scans)
    kept, volts, noise, usable, stride, alone, ok = expected(s, rate, margin, max_scans)
    assert got.rows[:, 0].tolist() == kept and np.array_equal(got.rows[:, 1], got.rows[:, 0] + 1)
    np.testing.assert_allclose(got.volts, volts, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got.scan_noise[0] if len(got) else noise, noise, atol=1e-12)
    assert got.usable == usable and got.stride == stride
    assert np.array_equal(got.counts, np.ones(len(kept)))
    # every scan read is accounted for, once
    assert len(got) + sum(got.dropped.values()) == len(s), got.dropped
    assert got.dropped["no usable neighbour to correct its channel skew"] == alone
    thinned = {k: v for k, v in got.dropped.items() if k.startswith("thinned")}
    assert sum(thinned.values()) == usable - len(kept)
    if len(s) and rate:
        assert got.block.tolist() == [r // round(5 * rate) for r in kept]
