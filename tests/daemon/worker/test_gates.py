"""The acceptance gates after issue #16: the holdout gate's chi-square quantile without
scipy.special (a fifth of a second to import), and the coverage advice made only when a
gate fails and needs it. Same limits, same verdicts, same advice."""

import numpy as np
import pytest
from scipy.special import chdtri

from loopcal.calibration.simulate import simulate_poses
from loopcal.daemon.worker import coverage as C
from loopcal.daemon.worker.gates import fit as P
from loopcal.daemon.worker.gates import residual as G
from loopcal.daemon.worker.gates.chi2 import chi2_quantile


@pytest.mark.parametrize("tail", [0.001, 0.01, 0.1, 1e-6])
def test_chi2_quantile_is_scipys(tail):
    dofs = [*range(1, 400), 500, 1000, 1999, 5000, 6062, 10_000, 30_311, 100_000, 1_000_000]
    for dof in dofs:
        assert chi2_quantile(dof, tail) == pytest.approx(chdtri(dof, tail), rel=1e-12, abs=0)


def test_chi2_quantile_refuses_what_it_was_not_made_for():
    for dof, tail in ((0, 0.001), (5, 0.5), (5, 0.0)):
        with pytest.raises(ValueError):
            chi2_quantile(dof, tail)


def test_holdout_gate_as_before():
    rng = np.random.default_rng(0)
    for n in (4, 5, 9, 40, 1259, 6062):
        for scale in (0.9, 1.0, 1.3, 2.5):
            z = rng.normal(0, scale, n)
            gate = G.holdout_gate(z)
            if n < 5:
                assert not gate.passed
                continue
            rms = float(np.sqrt(np.mean(z**2)))
            limit = G.HOLDOUT_MARGIN * float(np.sqrt(chdtri(n, 0.001) / n))
            assert gate.passed == (rms <= limit)
            assert gate.limit == f"<= {limit:.2f} (RMS in predicted standard deviations, {n} poses)"


def test_advice_is_made_only_for_a_failing_gate(monkeypatch):
    ps = simulate_poses(60, seed=3)
    volts, params = ps.volts, ps.truth
    calls = []
    original = C.coverage_move

    def counted(v, p, **kw):
        calls.append(1)
        return original(v, p, **kw)

    monkeypatch.setattr(C, "coverage_move", counted)
    advice = C.lazy_coverage_advice(volts, params)
    assert P.condition_gate(10.0, advice).passed
    assert P.min_singular_gate(1.0, advice).passed
    assert P.precision_gate(["d01"], np.array([0.01]), advice).passed
    assert calls == [] and not advice.made
    failed = [
        P.condition_gate(1e4, advice),
        P.min_singular_gate(0.01, advice),
        P.precision_gate(["d01"], np.array([1.0]), advice),
    ]
    assert len(calls) == 1  # made once, for all three
    monkeypatch.undo()
    expected = C.coverage_advice(volts, params)
    assert all(not g.passed and g.advice == expected for g in failed)
    assert P.condition_gate(1e4, expected).advice == expected  # the text still works
