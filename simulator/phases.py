"""A robot's day in phases: one scenario after another (the task loop, then a technician's
hand, then the task loop again), for scripted lives of the mechanism.

Each phase's scenario sees its own time, from 0 at the phase's start: a hand that takes
over from the task loop begins its moves afresh. The plate goes from one phase's
orientation to the next's within a scan, as a scripted life needs no more.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .motion import Scenario


class Phases(Scenario):
    """Scenarios in turn, each from its start time on.

    Parameters
    ----------
    phases : sequence of (float, Scenario)
        (start s of source time, scenario), the first starting at 0, in increasing order.

    Raises
    ------
    ValueError
        If there is no phase, the first does not start at 0, or the starts do not
        increase.
    """

    name = "phases"

    def __init__(self, phases: Sequence[tuple[float, Scenario]]) -> None:
        starts = [float(t) for t, _ in phases]
        if not starts or starts[0] != 0.0:
            raise ValueError("phases: the first phase must start at 0 s")
        if any(b <= a for a, b in zip(starts, starts[1:], strict=False)):
            raise ValueError("phases: each phase must start after the one before")
        self.starts = np.array(starts)
        self.scenarios = [s for _, s in phases]

    def rotation(self, t: np.ndarray) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        which = np.searchsorted(self.starts, t, side="right") - 1
        which = np.clip(which, 0, len(self.scenarios) - 1)
        out = np.empty((len(t), 3, 3))
        for k in np.unique(which):
            sel = which == k
            out[sel] = self.scenarios[k].rotation(t[sel] - self.starts[k])
        return out

    def describe(self) -> dict:
        return {
            "name": self.name,
            "phases": [
                {"start_s": float(a), **s.describe()}
                for a, s in zip(self.starts, self.scenarios, strict=True)
            ],
        }
