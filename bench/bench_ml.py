"""Maximum likelihood ("ml") against the paper's closed-loop residuals ("paper"): accuracy
against the Cramér-Rao bound, time against pose count, and real recorded sessions.

Four parts, all run by default (``--part`` runs one):

``mc``: Monte Carlo over ``--sessions`` simulated sessions (450 random single-scan poses of
a random mechanism, 40 mV, quantised). ``calibrate(method="ml")`` selects 50 poses and its
identification is the ml estimate; the paper's method identifies from the SAME 50 poses. The
Cramér-Rao bound (CRLB) of each session's pose set, at the true rotations and parameters,
scales that session's errors. Per parameter and method: RMS error, RMS of error / CRLB std
("RMS/CRLB", 1 is the best any unbiased estimator can do), the mean error and mean z with
their standard errors ("biased" when |mean z| exceeds three of them), the median of the
method's own reported std over the CRLB std (honesty of the reported uncertainty), RMS of
error / own std, 1.4826 median |z| ("MAD/CRLB", blind to the few sessions where a method
drops poses) and RMS/CRLB over the sessions where the method used all 50 poses, and
failures. The paper's method is the baseline; target: ml's RMS/CRLB at most 1.05 for every
parameter. Wall time is printed (``--jobs`` processes, one BLAS thread each).

``scale``: ``identify(method="ml")`` end to end on 500 .. 20,000 poses (median of
``--repeats``): iterations, ms per iteration and us per pose per iteration, which should stay
flat (linear cost), and the same per model evaluation (rejected LM trial steps cost one too,
counted in a separate, untimed run). Baseline in the same run: the paper's method, end to
end, up to 10,000 poses. Target: 10,000 poses in under 1 s.

``anchor``: the expert's alternative on exactly the same problem: scipy's
``least_squares(method="trf", tr_solver="lsmr")`` on the free parameters plus one rotation
increment per pose (``R_k = exp([w_k]x) R0_k``), the same readings, weights, start rotations
(forward kinematics at the start) and start parameters, given the analytic block-sparse
Jacobian (``implicit.model_jacobians`` times the left Jacobian of SO(3)) as a CSR matrix;
lsmr's tolerances at 1e-10 (at its default 1e-6, trf stops 4e-3 to 9e-3 standard deviations
short of the minimum). Timed against ``identify(method="ml")`` end to end (start rotations,
passes, covariance and indices included; the anchor's time is the solver's alone), median of
``--repeats`` (at least 3), alternating, in one worker process with one BLAS thread (OpenBLAS
threads on a shared two-core machine slow lsmr's vector operations by 3 to 10 times).
Same minimum: the whitened costs within 1e-9 relative and every free parameter within 1e-3
of its standard deviation. Target: ours at least 3 times faster at 10,000 and 30,000 poses.

``sessions``: technician sessions at the paper's noise recorded through the real
``loopcal simulate`` + ``loopcal record`` subprocesses (``--seeds``, three at a time), cut to
exactly two minutes and calibrated by ``loopcal calibrate --json`` with ``--method ml`` and
``--method paper`` on the same recording. Per method: RMS error over the seeds, max |error|,
RMS and mean of error / reported std, and how many were accepted (``--dir`` keeps the cut
recordings and reuses them on the next run). Targets (ml): RMS error < 0.1 mm for
d01..d04 and < 0.15 mm for A1x, A2x, A2y.

Run: ``python -m bench.bench_ml [--part mc|scale|anchor|sessions] [--sessions 200] [--jobs 2]
[--repeats 3] [--seeds 101 102 ...] [--dir DIR]``.
"""

from __future__ import annotations

import argparse
import importlib
import multiprocessing as mp
import os
import shutil
import statistics
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import scipy.sparse as sparse
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from bench._timing import median_time
from loopcal.calibration import implicit
from loopcal.calibration.identify import identify
from loopcal.calibration.implicit import cramer_rao, start_rotations
from loopcal.calibration.parameters import INDEX, NOMINAL, PAPER7
from loopcal.calibration.pipeline import calibrate
from loopcal.calibration.simulate import simulate_poses

METHODS = ("ml", "paper")
NOISE_VOLTS = 0.040
LSB_VOLTS = 20.0 / 4096
#: the readings' noise after the 12-bit converter: Gaussian noise plus uniform rounding
SIGMA_VOLTS = float(np.sqrt(NOISE_VOLTS**2 + LSB_VOLTS**2 / 12))
N_POSES, N_SELECT = 450, 50
ML_TARGET = 1.05
SCALE_SIZES = (500, 1000, 2000, 5000, 10000, 20000)
PAPER_MAX_POSES = 10000
SESSION_TARGETS = {"d01": 0.1, "d02": 0.1, "d03": 0.1, "d04": 0.1}
SESSION_TARGETS |= {"A1x": 0.15, "A2x": 0.15, "A2y": 0.15}
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
ANCHOR_SIZES = (10000, 30000)
ANCHOR_TARGET = 3.0
#: lsmr's atol and btol in the anchor (scipy's default 1e-6 leaves trf short of the minimum)
ANCHOR_LSMR_TOL = 1e-10
#: "the same minimum": whitened costs within this relative difference ...
SAME_COST_RTOL = 1e-9
#: ... and every free parameter within this fraction of its standard deviation
SAME_PARAM_STD = 1e-3


# ---------------------------------------------------------------------------- Monte Carlo


def mc_session(seed: int) -> dict:
    """One simulated session: errors of both methods on the same poses, and the CRLB."""
    out: dict = {"seed": seed}
    ps = simulate_poses(N_POSES, seed=seed, noise_volts=NOISE_VOLTS)
    truth = PAPER7.free_values(ps.truth)
    try:
        cal = calibrate(ps.volts, PAPER7, NOMINAL, n_select=N_SELECT, method="ml")
    except Exception as exc:  # counted; the run carries on
        out["ml"] = {"failed": f"{type(exc).__name__}: {exc}"}
        return out  # no pose set: the paper's method has nothing to run on
    idx = cal.selection.indices
    crlb = cramer_rao(ps.rotations[idx], ps.truth, PAPER7.tie_matrix, noise_volts=SIGMA_VOLTS)
    out["crlb"] = np.sqrt(np.diag(crlb))
    out["n"] = len(idx)
    results = {"ml": lambda: cal.identification}
    results["paper"] = lambda: identify(ps.volts[idx], PAPER7, NOMINAL, method="paper")
    for method, get in results.items():
        try:
            r = get()
        except Exception as exc:
            out[method] = {"failed": f"{type(exc).__name__}: {exc}"}
            continue
        out[method] = {
            "err": PAPER7.free_values(r.params) - truth,
            "std": np.asarray(r.std),
            "converged": bool(r.converged),
            "used": int(np.sum(r.used)),
            "iterations": int(r.iterations),
        }
    return out


def _one_thread_workers() -> None:
    for var in THREAD_VARS:
        os.environ[var] = "1"


@contextmanager
def _environment(values: dict[str, str]):
    """Set environment variables for the duration (spawned workers inherit them before they
    import numpy, so the BLAS thread count takes)."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def run_mc(n_sessions: int, jobs: int, first_seed: int) -> None:
    print(
        f"== mc: {n_sessions} simulated sessions, {N_POSES} single-scan poses each, "
        f"{1000 * NOISE_VOLTS:.0f} mV, quantised; {N_SELECT} selected by calibrate(ml), both "
        "methods on the same poses"
    )
    print(
        f"   CRLB at the true rotations and parameters, sigma = sqrt({NOISE_VOLTS}^2 + LSB^2/12)"
        f" = {1000 * SIGMA_VOLTS:.3f} mV (LSB = 20 V / 4096: the converter's rounding adds "
        "LSB^2/12)"
    )
    seeds = list(range(first_seed, first_seed + n_sessions))
    t0 = time.perf_counter()
    if jobs > 1:
        with _environment({v: "1" for v in THREAD_VARS}):
            ctx = mp.get_context("spawn")
            with ctx.Pool(jobs, initializer=_one_thread_workers) as pool:
                rows = pool.map(mc_session, seeds, chunksize=4)
    else:
        rows = [mc_session(s) for s in seeds]
    wall = time.perf_counter() - t0
    names = PAPER7.free
    verdicts = []
    for method in METHODS:
        ok = [r for r in rows if method in r and "failed" not in r[method]]
        failed = [r for r in rows if method in r and "failed" in r[method]]
        skipped = n_sessions - len(ok) - len(failed)
        print()
        print(
            f"-- {method}: {len(ok)} sessions, {len(failed)} failed"
            + (f", {skipped} not run (no pose set)" if skipped else "")
            + f", {sum(not r[method]['converged'] for r in ok)} not converged"
            + (
                f"; poses used median {statistics.median(r[method]['used'] for r in ok):.0f}"
                f" (min {min(r[method]['used'] for r in ok)}) of {N_SELECT}"
                f"; iterations median {statistics.median(r[method]['iterations'] for r in ok):.0f}"
                if ok
                else ""
            )
        )
        for r in failed[:5]:
            print(f"   seed {r['seed']}: {r[method]['failed']}")
        if not ok:
            verdicts.append((method, float("nan"), 0, ""))
            continue
        err = np.array([r[method]["err"] for r in ok])
        std = np.array([r[method]["std"] for r in ok])
        crlb = np.array([r["crlb"] for r in ok])
        z = err / crlb
        k = len(ok)
        print(
            f"   {'param':>5} {'RMS err':>8} {'RMS/CRLB':>8} {'mean err +- se':>17} "
            f"{'mean z +- se':>15} {'':>6} {'std/CRLB':>8} {'RMS err/std':>11} {'MAD/CRLB':>8} "
            f"{'all-used':>8}"
        )
        full = np.array([r[method]["used"] == r["n"] for r in ok])
        ratios = []
        for j, name in enumerate(names):
            e, zz = err[:, j], z[:, j]
            rms_z = float(np.sqrt(np.mean(zz**2)))
            ratios.append(rms_z)
            se_e = float(np.std(e, ddof=1) / np.sqrt(k))
            se_z = float(np.std(zz, ddof=1) / np.sqrt(k))
            biased = "biased" if abs(np.mean(zz)) > 3 * se_z else ""
            print(
                f"   {name:>5} {np.sqrt(np.mean(e**2)):8.4f} {rms_z:8.3f} "
                f"{np.mean(e):+8.4f} +- {se_e:6.4f} {np.mean(zz):+6.3f} +- {se_z:5.3f} "
                f"{biased:>6} {np.median(std[:, j] / crlb[:, j]):8.3f} "
                f"{np.sqrt(np.mean((e / std[:, j]) ** 2)):11.3f} "
                f"{1.4826 * np.median(np.abs(zz)):8.3f} "
                f"{np.sqrt(np.mean(zz[full] ** 2)) if full.any() else np.nan:8.3f}"
            )
        worst = int(np.argmax(ratios))
        verdicts.append((method, ratios[worst], k, names[worst]))
        print(
            "   (errors in mm; z = error / that session's CRLB std; MAD/CRLB = 1.4826 median |z|,\n"
            "    what RMS/CRLB would be without outliers; all-used: RMS/CRLB over the "
            f"{int(full.sum())} sessions\n    where the method used all {N_SELECT} poses)"
        )
    print()
    for v in verdicts:
        method, worst = v[0], v[1]
        if v[2] == 0:
            print(f"verdict {method}: no successful session")
            continue
        # the RMS of k Gaussian z's is known to about 1/sqrt(2k)
        se = worst / np.sqrt(2 * v[2])
        line = f"verdict {method:>5}: max RMS/CRLB {worst:.3f} +- {se:.3f} ({v[3]})"
        if method == "ml":
            line += f"; target <= {ML_TARGET}: {'met' if worst <= ML_TARGET else 'NOT met'}"
        else:
            line += " (baseline)"
        print(line)
    print(f"wall time {wall:.1f} s ({jobs} process(es))")


# ---------------------------------------------------------------------------- scale


@contextmanager
def _counting(module, name: str):
    """Count the calls of ``module.name`` (the model evaluations of a fit) while inside."""
    original = getattr(module, name)
    calls = [0]

    def counted(*args, **kwargs):
        calls[0] += 1
        return original(*args, **kwargs)

    setattr(module, name, counted)
    try:
        yield calls
    finally:
        setattr(module, name, original)


def evaluations(volts: np.ndarray, method: str) -> int:
    """Model evaluations (residuals and Jacobians of every pose) one identify() makes:
    accepted and rejected LM steps (ml: ``implicit._evaluate``, whose last one also gives
    the covariance; the paper's method: ``loop_residuals``, the covariance included)."""
    # the package exports the function identify(), which hides its module's name
    ident_mod = importlib.import_module("loopcal.calibration.identify")
    implicit_mod = importlib.import_module("loopcal.calibration.implicit")
    if method == "ml":
        module, name = implicit_mod, "_evaluate"
    else:
        module, name = ident_mod, "loop_residuals"
    with _counting(module, name) as calls:
        identify(volts, PAPER7, NOMINAL, method=method)
    return calls[0]


def run_scale(repeats: int) -> None:
    print(
        f"== scale: identify() end to end, median of {repeats}; "
        f"simulate_poses(m, seed=1), {1000 * NOISE_VOLTS:.0f} mV"
    )
    print(
        f"   {'method':>6} {'poses':>6} {'iter':>5} {'conv':>5} {'total s':>8} {'ms/iter':>8} "
        f"{'us/pose/iter':>12} {'evals':>5} {'us/pose/eval':>12} {'FK start s':>10}"
    )
    times: dict[tuple[str, int], float] = {}
    per: dict[tuple[str, int], float] = {}
    per_eval: dict[tuple[str, int], float] = {}
    stalled = []
    for m in SCALE_SIZES:
        ps = simulate_poses(m, seed=1, noise_volts=NOISE_VOLTS)
        t_fk, _ = median_time(lambda ps=ps: start_rotations(ps.volts, NOMINAL), repeats)
        for method in METHODS:
            if method == "paper" and m > PAPER_MAX_POSES:
                continue
            t, r = median_time(
                lambda ps=ps, method=method: identify(ps.volts, PAPER7, NOMINAL, method=method),
                repeats,
            )
            it = max(r.iterations, 1)
            ev = evaluations(ps.volts, method)  # a run of its own: the timed ones are bare
            times[method, m] = t
            per[method, m] = 1e6 * t / it / m
            per_eval[method, m] = 1e6 * t / max(ev, 1) / m
            if not r.converged:
                stalled.append(f"{method} at {m} poses: {r.message}")
            fk = f"{t_fk:10.3f}" if method == "ml" else f"{'':>10}"
            print(
                f"   {method:>6} {m:6d} {r.iterations:5d} {'yes' if r.converged else 'NO':>5} "
                f"{t:8.3f} {1000 * t / it:8.2f} {per[method, m]:12.2f} {ev:5d} "
                f"{per_eval[method, m]:12.2f} {fk}",
                flush=True,
            )
    print("   (iter: LM iterations over all passes; evals: model evaluations, rejected LM trial")
    print("    steps and the covariance included (ml's covariance reuses its last); FK start: the")
    print("    forward kinematics that ml starts its rotations from, inside the total; each pass")
    print("    then judges the poses again by forward kinematics from the fitted rotations)")
    for line in stalled:
        print(f"   not converged: {line}")
    print()
    for method in METHODS:
        a, b = times.get((method, 1000)), times.get((method, 10000))
        if a and b:
            print(
                f"{method:>5}: time(10000)/time(1000) = {b / a:.1f} (10x the poses); per pose "
                f"per iteration {per[method, 10000] / per[method, 1000]:.2f}x, per pose per "
                f"evaluation {per_eval[method, 10000] / per_eval[method, 1000]:.2f}x"
            )
    if ("ml", 10000) in times and ("paper", 10000) in times:
        t_ml, t_p = times["ml", 10000], times["paper", 10000]
        print(f"10,000 poses: ml {t_ml:.3f} s, paper {t_p:.3f} s (ml/paper {t_ml / t_p:.2f})")
    if ("ml", 10000) in times:
        t = times["ml", 10000]
        print(f"target: ml on 10,000 poses < 1 s: {'met' if t < 1 else 'NOT met'} ({t:.3f} s)")


# ---------------------------------------------------------------------------- anchor


def _exp_and_left_jacobian(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """exp([w]x) (m, 3, 3) and the left Jacobian of SO(3) at w (m, 3, 3), for w (m, 3):
    ``exp(w + d) = exp(Jl(w) d) exp(w)`` to first order in d."""
    t2 = np.einsum("mi,mi->m", w, w)
    t = np.sqrt(t2)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / ts**3)
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    Jl = np.eye(3) + b[:, None, None] * K + c[:, None, None] * (K @ K)
    return Rotation.from_rotvec(w).as_matrix(), Jl


def anchor_fit(volts, weights, R0, directions, p_start):
    """scipy's least_squares (trf, lsmr) on the maximum-likelihood problem of
    :func:`loopcal.calibration.implicit.fit_linearised`: unknowns z = (dx (n,), w (m, 3)),
    ``p = p_start + T dx``, ``R_k = exp([w_k]x) R0_k``, residuals ``(Vhat - V) * weights``
    (4m,), from z = 0, with the analytic Jacobian as a CSR matrix (each row: n parameter
    entries and its pose's 3).
    Returns (params, rotations (m, 3, 3), the OptimizeResult)."""
    m, n = len(volts), directions.shape[1]
    rows = 4 * m
    cols = np.concatenate(
        [
            np.broadcast_to(np.arange(n), (rows, n)),
            n + 3 * np.repeat(np.arange(m), 4)[:, None] + np.arange(3),
        ],
        axis=1,
    ).ravel()
    indptr = np.arange(rows + 1) * (n + 3)

    def unpack(z):
        return p_start + directions @ z[:n], z[n:].reshape(m, 3)

    def fun(z):
        p, w = unpack(z)
        R = Rotation.from_rotvec(w).as_matrix() @ R0
        return ((implicit.predicted_volts(R, p) - volts) * weights).ravel()

    def jac(z):
        p, w = unpack(z)
        E, Jl = _exp_and_left_jacobian(w)
        _, Jp, Jr = implicit.model_jacobians(E @ R0, p, directions)
        wt = weights[..., None]
        data = np.concatenate([(Jp * wt).reshape(rows, n), ((Jr @ Jl) * wt).reshape(rows, 3)], 1)
        return sparse.csr_matrix((data.ravel(), cols, indptr), shape=(rows, n + 3 * m))

    tol = {"atol": ANCHOR_LSMR_TOL, "btol": ANCHOR_LSMR_TOL}
    res = least_squares(
        fun, np.zeros(n + 3 * m), jac=jac, method="trf", tr_solver="lsmr", tr_options=tol
    )
    p, w = unpack(res.x)
    return p, Rotation.from_rotvec(w).as_matrix() @ R0, res


def _whitened_cost(volts, weights, R, p) -> float:
    """sum ((V - Vhat) weights)^2 at (R, p): the objective both fits minimise."""
    r = (volts - implicit.predicted_volts(R, p)) * weights
    return float(np.sum(r * r))


def anchor_rows(sizes: tuple[int, ...], repeats: int) -> list[dict]:
    """Time the anchor and identify(ml) on simulate_poses(m, seed=1) for each size, and
    compare their minima (run in a worker process with one BLAS thread)."""
    out = []
    model, T = PAPER7, PAPER7.tie_matrix
    for m in sizes:
        ps = simulate_poses(m, seed=1, noise_volts=NOISE_VOLTS)
        V = ps.volts
        w = implicit.pose_weights(m, None, None)  # identify's weights without noise_volts
        R0, usable = start_rotations(V, NOMINAL)  # the rotations identify() starts from
        t_ours, t_anchor = [], []
        for _ in range(max(repeats, 3)):  # alternating, so both see the same load
            t0 = time.perf_counter()
            ours = identify(V, model, NOMINAL, method="ml")
            t_ours.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            p_a, R_a, res = anchor_fit(V[usable], w[usable], R0[usable], T, NOMINAL)
            t_anchor.append(time.perf_counter() - t0)
        same_poses = bool(np.array_equal(ours.used, usable))
        cost_ours = _whitened_cost(V[ours.used], w[ours.used], ours.rotations, ours.params)
        cost_anchor = _whitened_cost(V[usable], w[usable], R_a, p_a)
        dz = (model.free_values(p_a) - model.free_values(ours.params)) / ours.std
        out.append(
            {
                "m": m,
                "usable": int(usable.sum()),
                "repeats": len(t_ours),
                "anchor": statistics.median(t_anchor),
                "ours": statistics.median(t_ours),
                "cost_anchor": cost_anchor,
                "cost_ours": cost_ours,
                "dz": float(np.abs(dz).max()),
                "worst": model.free[int(np.argmax(np.abs(dz)))],
                "same_poses": same_poses,
                "nfev": int(res.nfev),
                "njev": int(res.njev),
                "status": int(res.status),
                "iterations": int(ours.iterations),
                "converged": bool(ours.converged),
            }
        )
    return out


def run_anchor(repeats: int) -> None:
    print(
        '== anchor: scipy least_squares(method="trf", tr_solver="lsmr", lsmr atol = btol = '
        f"{ANCHOR_LSMR_TOL:g}) with the analytic sparse Jacobian, on the same problem as "
        f'identify(method="ml"): simulate_poses(m, seed=1), {1000 * NOISE_VOLTS:.0f} mV, paper7'
    )
    print(
        "   anchor: the solver alone (start rotations given); ours: identify() end to end; "
        f"median of {max(repeats, 3)}, alternating, one process with one BLAS thread"
    )
    with _environment({v: "1" for v in THREAD_VARS}):
        ctx = mp.get_context("spawn")
        with ctx.Pool(1, initializer=_one_thread_workers) as pool:
            rows = pool.apply(anchor_rows, (ANCHOR_SIZES, repeats))
    print(
        f"   {'poses':>6} {'anchor s':>9} {'ours s':>8} {'anchor/ours':>11} "
        f"{'cost anchor':>13} {'cost ours':>13} {'rel diff':>9} {'max|dx|/std':>11} "
        f"{'nfev':>5} {'iter':>5}"
    )
    verdicts = []
    for r in rows:
        ratio = r["anchor"] / r["ours"]
        rel = (r["cost_anchor"] - r["cost_ours"]) / r["cost_ours"]
        same = (
            r["same_poses"]
            and abs(rel) <= SAME_COST_RTOL
            and r["dz"] <= SAME_PARAM_STD
            and r["converged"]
        )
        verdicts.append((r["m"], ratio, same))
        print(
            f"   {r['m']:6d} {r['anchor']:9.3f} {r['ours']:8.3f} {ratio:11.2f} "
            f"{r['cost_anchor']:13.9g} {r['cost_ours']:13.9g} {rel:+9.1e} "
            f"{r['dz']:11.1e} {r['nfev']:5d} {r['iterations']:5d}"
        )
        if not r["same_poses"]:
            print(f"   {r['m']} poses: ours ended on another pose set than the anchor's")
    print(
        "   (cost: sum of squared whitened residuals, unit weights; rel diff: anchor over ours "
        "minus 1;\n    max|dx|/std: the largest difference of a free parameter over ours' std; "
        "nfev: the anchor's\n    function evaluations; iter: ours' LM iterations)"
    )
    print(
        f"same minimum (cost within {SAME_COST_RTOL:g} relative, parameters within "
        f"{SAME_PARAM_STD:g} std): " + ("yes" if all(v[2] for v in verdicts) else "NO")
    )
    met = all(v[1] >= ANCHOR_TARGET for v in verdicts)
    print(
        "anchor/ours: "
        + ", ".join(f"{m:,} poses {ratio:.1f}x" for m, ratio, _ in verdicts)
        + f"; target >= {ANCHOR_TARGET:g}x: {'met' if met else 'NOT met'}"
    )


# ---------------------------------------------------------------------------- sessions


def run_sessions(seeds: list[int], directory: Path | None) -> None:
    from loopcal.daemon.recording import find_recordings
    from tests.support.processes import calibrate_json, fresh_config
    from tests.support.sessions import live_sessions, trim, truth_for

    print(
        f"== sessions: {len(seeds)} technician sessions, 40 mV, recorded through loopcal "
        "simulate + loopcal record (3 at a time, 10x speed), cut to exactly two minutes "
        "(scans 600..2999), calibrated by loopcal calibrate --json --method ml|paper"
    )
    with tempfile.TemporaryDirectory(prefix="bench_ml_") as tmp:
        root = directory if directory is not None else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        print(f"   recordings under {root}")
        t0 = time.perf_counter()
        two: dict[int, Path] = {}
        todo = []
        for s in seeds:
            d = root / f"two-{s}"
            if d.is_dir() and find_recordings(d):
                two[s] = d  # a cached cut (the truth follows from the seed)
            else:
                todo.append(s)
        for b in range(0, len(todo), 3):
            batch = todo[b : b + 3]
            for old in batch:
                src = root / f"session-{old}"
                if src.exists():  # a partial earlier run: start afresh
                    shutil.rmtree(src)
            try:
                recorded = live_sessions(root, batch, minutes=2.7, speed=10.0)
            except Exception as exc:
                lines = [x for x in str(exc).splitlines() if x.strip()] or [""]
                tail = f" ... {lines[-1].strip()}" if len(lines) > 1 else ""
                print(f"   recording seeds {batch} failed: {type(exc).__name__}: {lines[0]}{tail}")
                continue
            for sess in recorded:
                try:
                    two[sess.seed] = trim(sess.directory, root / f"two-{sess.seed}", 600, 3000)
                except AssertionError as exc:
                    print(f"   seed {sess.seed}: {exc}")
        t_rec = time.perf_counter() - t0
        cached = len(seeds) - len(todo)
        print(
            f"   recorded {len(todo)} session(s) in {t_rec:.0f} s"
            + (f", {cached} cached" if cached else "")
            + f"; {len(two)} of {len(seeds)} usable"
        )
        t0 = time.perf_counter()
        results: dict[str, list] = {m: [] for m in METHODS}
        failures: dict[str, list] = {m: [] for m in METHODS}
        for s in seeds:
            if s not in two:
                continue
            truth = truth_for(s)
            config = fresh_config(root / f"controller-{s}.toml")
            for method in METHODS:
                rc, doc, err = calibrate_json(
                    two[s], "--controller-config", config, "--method", method
                )
                if not doc.get("parameters"):
                    failures[method].append((s, rc, err.strip().splitlines()[-1:] or [""]))
                    continue
                e = {n: doc["parameters"][n]["value"] - truth[INDEX[n]] for n in PAPER7.free}
                sd = {n: doc["parameters"][n]["std"] for n in PAPER7.free}
                refused = [g["name"] for g in doc.get("gates", []) if not g.get("passed")]
                poses = doc.get("poses", {})
                results[method].append(
                    (s, e, sd, bool(doc.get("accepted")), refused, poses.get("selected", 0))
                )
        t_cal = time.perf_counter() - t0
    print(f"   calibrated {2 * len(two)} times in {t_cal:.0f} s")
    for method in METHODS:
        rows = results[method]
        print()
        print(
            f"-- {method}: {len(rows)} calibrated, {sum(r[3] for r in rows)} accepted, "
            f"{len(failures[method])} failed"
            + (f"; median {statistics.median([r[5] for r in rows] or [0]):.0f} poses selected")
        )
        for r in rows:
            if not r[3]:
                print(f"   seed {r[0]}: refused by gate(s) {', '.join(r[4]) or '?'}")
        for s, rc, last in failures[method]:
            print(f"   seed {s}: rc {rc}: {last[0]}")
        if not rows:
            continue
        head = (
            f"   {'param':>5} {'RMS err':>8} {'max |err|':>9} {'RMS err/std':>11} "
            f"{'mean err/std +- se':>18}"
        )
        print(head + (f" {'target':>7}" if method == "ml" else ""))
        met = True
        for n in PAPER7.free:
            e = np.array([r[1][n] for r in rows])
            sd = np.array([r[2][n] for r in rows])
            rms = float(np.sqrt(np.mean(e**2)))
            se = np.std(e / sd, ddof=1) / np.sqrt(len(e)) if len(e) > 1 else np.nan
            line = (
                f"   {n:>5} {rms:8.4f} {np.max(np.abs(e)):9.4f} "
                f"{np.sqrt(np.mean((e / sd) ** 2)):11.3f} {np.mean(e / sd):+9.2f} +- {se:5.2f}"
            )
            if method == "ml":
                ok = rms < SESSION_TARGETS[n]
                met &= ok
                line += f"  < {SESSION_TARGETS[n]:.2f} {'met' if ok else 'NOT met'}"
            print(line)
        print("   (errors in mm, against the simulated truth; std: the command's reported std)")
        if method == "ml":
            print(f"ml session targets: {'all met' if met else 'NOT all met'}")
    if len(results["ml"]) and len(results["paper"]):
        both = {r[0] for r in results["ml"]} & {r[0] for r in results["paper"]}
        ratio = []
        for n in PAPER7.free:
            ml = np.array([r[1][n] for r in results["ml"] if r[0] in both])
            pp = np.array([r[1][n] for r in results["paper"] if r[0] in both])
            ratio.append(f"{n} {np.sqrt(np.mean(pp**2) / np.mean(ml**2)):.2f}")
        print(f"RMS error paper/ml on the same {len(both)} recordings: " + ", ".join(ratio))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("mc", "scale", "anchor", "sessions"), default=None)
    ap.add_argument("--sessions", type=int, default=200, help="Monte Carlo sessions (200)")
    ap.add_argument("--first-seed", type=int, default=1, help="first Monte Carlo seed (1)")
    ap.add_argument("--jobs", type=int, default=2, help="Monte Carlo processes (2)")
    ap.add_argument("--repeats", type=int, default=3, help="timing repeats (3)")
    ap.add_argument(
        "--seeds", type=int, nargs="+", default=list(range(101, 113)), help="session seeds"
    )
    ap.add_argument("--dir", type=Path, default=None, help="keep the recordings here")
    args = ap.parse_args()
    parts = [args.part] if args.part else ["mc", "scale", "anchor", "sessions"]
    for i, part in enumerate(parts):
        if i:
            print()
        if part == "mc":
            run_mc(args.sessions, args.jobs, args.first_seed)
        elif part == "scale":
            run_scale(args.repeats)
        elif part == "anchor":
            run_anchor(args.repeats)
        else:
            run_sessions(args.seeds, args.dir)
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
