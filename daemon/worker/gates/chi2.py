"""The chi-square quantile the gates' limits are made of, without scipy.

Not ``scipy.special.chdtri``, for ``loopcal calibrate``'s start-up (issue 31 measured it:
medians of 15 fresh processes, interleaved, on a loaded 2-core machine): scipy.special costs
0.22 to 0.25 s of imports in that process (``python -X importtime``; nothing else in it
imports any scipy), and ``loopcal calibrate`` of a two-minute recording would take 1.96x
``import numpy, scipy.linalg`` instead of 1.51x, against a target of at most 2x
(docs/architecture.md, "Start-up"; one run of 7 gave 2.02x). Imported with the module it
would also cost ``loopcal calibrate --help`` 1.49x instead of about 0.95x. If scipy.special is
ever imported on this path for another reason, :func:`chi2_quantile` should become
``chdtri(dof, tail)``: tests/daemon/worker/test_gates.py holds the two equal.
"""

from __future__ import annotations

import math
from statistics import NormalDist


def _log_upper_gamma(a: float, t: float) -> tuple[float, float]:
    """log Q(a, t), the regularized upper incomplete gamma function, and its derivative
    with respect to t, by the continued fraction (modified Lentz; it converges quickly for
    t > a + 1, where the upper tail's quantiles lie for every a but the smallest)."""
    tiny = 1e-300
    b = t + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / (b if abs(b) >= tiny else tiny)
    h = d
    for i in range(1, 100_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < 1e-16:
            break
    log_density = -t + (a - 1.0) * math.log(t) - math.lgamma(a)  # d(-Q)/dt
    log_q = log_density + math.log(t) + math.log(h)
    return log_q, -math.exp(log_density - log_q)


def chi2_quantile(dof: int, tail: float) -> float:
    """The upper ``tail`` quantile of the chi-square distribution with ``dof`` degrees.

    The value a chi-square variable of ``dof`` degrees of freedom exceeds with probability
    ``tail``, as ``scipy.special.chdtri(dof, tail)`` gives it (why not that: the module's
    docstring): Newton's method on log Q(dof / 2, x / 2) from the Wilson-Hilferty
    approximation (tests/daemon/worker/test_gates.py compares the two).

    Parameters
    ----------
    dof : int
        Degrees of freedom, >= 1.
    tail : float
        The upper tail's probability, 0 < tail <= 0.1.

    Returns
    -------
    float
        The upper ``tail`` quantile of chi-square with ``dof`` degrees of freedom.

    Raises
    ------
    ValueError
        If ``dof`` < 1 or ``tail`` is outside (0, 0.1].
    """
    if not (dof >= 1 and 0.0 < tail <= 0.1):
        raise ValueError(f"chi2_quantile needs dof >= 1 and 0 < tail <= 0.1, got {dof}, {tail}")
    a, target = dof / 2.0, math.log(tail)
    z = NormalDist().inv_cdf(1.0 - tail)
    q = 2.0 / (9.0 * dof)
    t = max(a, 0.5 * dof * (1.0 - q + z * math.sqrt(q)) ** 3)
    last = math.inf
    for _ in range(100):
        log_q, slope = _log_upper_gamma(a, t)
        t_new = max(t - (log_q - target) / slope, 0.5 * t)
        moved = abs(t_new - t)
        t = t_new
        # quadratic convergence until rounding: stop at a step of a few ulps, or one no
        # smaller than the step before
        if moved <= 1e-14 * t or moved >= last:
            break
        last = moved
    return 2.0 * t
