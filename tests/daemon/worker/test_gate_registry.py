"""The acceptance gates as a list (issue 31): docs/calibration.md's table of gates is the one
explanation of them, and it holds every gate of the registry, in its order, with the limits
the gate uses; a new gate without its row fails here."""

import re

import numpy as np

from loopcal.calibration.parameters import PAPER7
from loopcal.daemon.worker.coverage import lazy_coverage_advice
from loopcal.daemon.worker.gates import GATES, GateContext, measure_gates
from loopcal.daemon.worker.recorded_poses import RecordedPoses
from tests.support import ROOT

ROW = re.compile(r"^\| `(\w+)` \|(.*)\|$")


def _table() -> dict[str, str]:
    """{gate: its row's text} of docs/calibration.md's table of gates, in order."""
    text = (ROOT / "docs" / "calibration.md").read_text(encoding="utf-8")
    start = text.index("| gate | passes when |")
    rows = {}
    for line in text[start:].splitlines()[2:]:
        m = ROW.match(line)
        if m is None:
            break
        rows[m[1]] = m[2]
    return rows


def test_every_gate_is_in_the_docs_with_its_limits():
    rows = _table()
    names = [c.name for c in GATES]
    assert len(set(names)) == len(names), names
    assert list(rows) == names, "docs/calibration.md's table of gates against the registry"
    for check in GATES:
        for limit in check.documented():
            assert limit in rows[check.name], (check.name, limit)


def test_before_the_fit_only_the_motion_is_judged():
    volts = np.random.default_rng(0).uniform(-5, 5, (40, 4))
    k = len(volts)
    poses = RecordedPoses(volts, np.zeros_like(volts), np.full_like(volts, 0.04), np.full(k, 20),
                          np.zeros((k, 2), int), np.zeros(k, int), 20.0)  # fmt: skip
    start = np.zeros(20)
    ctx = GateContext(poses, False, PAPER7, start, lazy_coverage_advice(volts, start))
    assert [g.name for g in measure_gates(ctx, before_fit=True)] == ["poses"]
    assert measure_gates(ctx, before_fit=False) == []  # no fit, no error: nothing to judge
    off = GateContext(poses, False, PAPER7, start, "", positions=False)
    assert measure_gates(off, before_fit=True) == []
    raised = GateContext(poses, False, PAPER7, start, "record again",
                         error=ValueError("diverged"))  # fmt: skip
    (gate,) = measure_gates(raised, before_fit=False)
    got = (gate.name, gate.passed, gate.value, gate.reason, gate.advice)
    assert got == ("converged", False, "ValueError", "diverged", "record again")
