"""``loopcal calibrate --report DIR``: one HTML page with plots a person would rather look at.

The page (``DIR/index.html``, plots as PNG beside it) shows whether the result was accepted
and why, the change of each parameter with its uncertainty, how well the loops close before
and after, how the minimum singular value grows with the number of poses selected, and where
the poses lie in the workspace.
"""

from __future__ import annotations

import html
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, no screen
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from loopcal.calibration import implicit  # noqa: E402
from loopcal.calibration.kinematics import (  # noqa: E402
    base_points,
    forward_kinematics,
    output_axis_angles,
    volts_to_lengths,
)
from loopcal.calibration.observability import column_scales  # noqa: E402
from loopcal.calibration.parameters import INDEX, UNITS  # noqa: E402
from loopcal.calibration.selection import candidate_jacobian, select_poses  # noqa: E402

from .gates.residual import holdout_residuals  # noqa: E402
from .job import METHOD_NAMES, WorkerResult  # noqa: E402


def save_figure(fig: plt.Figure, path: Path) -> None:
    """Write a figure as the report's (and ``loopcal check --plot``'s) PNGs are written,
    and free it."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _axis_angles(volts: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tilt (deg) and azimuth (rad) of the plate's output axis for each pose."""
    if len(volts) == 0:
        return np.zeros(0), np.zeros(0)
    R = forward_kinematics(volts_to_lengths(volts, params), params).rotations
    tilt, azimuth = output_axis_angles(R)
    return np.degrees(tilt), azimuth


def _plot_changes(res: WorkerResult, path: Path) -> None:
    names = list(res.model.free)
    fig, ax = plt.subplots(figsize=(7, 0.45 * len(names) + 1.2))
    y = np.arange(len(names))[::-1]
    change = [res.params[INDEX[n]] - res.previous[INDEX[n]] for n in names]
    std = [res.std.get(n, 0.0) for n in names]
    ax.errorbar(
        change,
        y,
        xerr=np.multiply(std, 3),
        fmt="o",
        capsize=4,
        color="tab:blue",
        label="change, +-3 standard deviations",
    )
    ax.axvline(0, color="grey", lw=0.8)
    ax.set_yticks(y, [f"{n} ({UNITS[n]})" for n in names])
    ax.set_xlabel("new - previous")
    ax.set_title("Change of each identified parameter")
    ax.legend(loc="best", fontsize=8)
    save_figure(fig, path)


def _plot_residuals(res: WorkerResult, path: Path) -> None:
    cal = res.calibration
    poses = res.poses
    chosen = res.fit[cal.indices] if cal is not None else res.fit
    before = 1000 * holdout_residuals(poses.volts[chosen], res.previous)
    after = 1000 * holdout_residuals(poses.volts[chosen], res.params)
    held = 1000 * holdout_residuals(poses.volts[res.held_out], res.params)
    fig, ax = plt.subplots(figsize=(7, 3.6))
    top = max(np.abs(np.concatenate([before, after, held, [1.0]])).max(), 1.0)
    bins = np.linspace(-top, top, 41)
    ax.hist(
        before,
        bins=bins,
        alpha=0.5,
        label=f"before (previous config), RMS {np.sqrt(np.mean(before**2)):.1f} mV",
        color="tab:red",
    )
    ax.hist(
        after,
        bins=bins,
        alpha=0.6,
        label=f"after, fitted poses, RMS {np.sqrt(np.mean(after**2)):.1f} mV",
        color="tab:green",
    )
    if len(held):
        ax.hist(
            held,
            bins=bins,
            histtype="step",
            lw=2,
            color="black",
            label=f"after, held-out poses, RMS {np.sqrt(np.mean(held**2)):.1f} mV",
        )
    ax.set_xlabel("loop-closure error of a pose, in mV of equivalent sensor noise")
    ax.set_ylabel("poses")
    ax.set_yscale("symlog")
    ax.set_title("How well the loops close, before and after")
    ax.legend(fontsize=8)
    save_figure(fig, path)


def _plot_singular_values_scans(res: WorkerResult, path: Path) -> None:
    """A fit on every scan selects nothing: how the singular values grew with the seconds of
    motion recorded (the fitted scans' information at the result, scaled as the fit's)."""
    ident = res.calibration.identification
    rows = implicit.weighted_information(ident.rotations, res.params, res.model.tie_matrix,
                                         np.ones((len(ident.rotations), 4)))  # fmt: skip
    seconds = (res.poses.rows[res.fit[res.calibration.indices][ident.used], 0] + 1) / max(
        res.poses.scan_rate_hz, 1e-9
    )
    n = res.model.n_free
    ends = sorted({int(k) for k in np.linspace(n, len(rows), 12)} | {len(rows)})
    ts, s_min, s_max = [], [], []
    for k in ends:
        a = rows[:k]
        sv = np.linalg.svd(a * column_scales(a[:, None, :], res.model.free), compute_uv=False)
        ts.append(seconds[k - 1])
        s_min.append(sv[-1])
        s_max.append(sv[0])
    _plot_singular_value_growth(
        ts, s_min, s_max, path, "seconds of the recording (every usable scan up to then)",
        "singular value (scaled information)", "Observability as the motion went on",
    )  # fmt: skip


def _plot_singular_values(res: WorkerResult, path: Path, progress: Callable[[str], None]) -> None:
    if res.calibration.selection is None:
        _plot_singular_values_scans(res, path)
        return
    volts = res.poses.volts[res.fit]
    cand = candidate_jacobian(volts, res.model, res.params)
    usable = int(cand.usable.sum())
    n = res.model.n_free
    ks = sorted(
        {k for k in (n, 10, 15, 20, 30, 40, 50, 75, 100, 150, 200, usable) if n <= k <= usable}
    )
    s_min, s_max = [], []
    for k in ks:
        progress(f"report: selecting {k} of {usable} poses")
        sel = select_poses(cand.jacobian, k, information=cand.information, certify=False)
        s_min.append(sel.indices_own.min_singular)
        s_max.append(float(sel.indices_own.singular_values[0]))
    _plot_singular_value_growth(
        ks, s_min, s_max, path, "poses selected (best of the recording)",
        "singular value (scaled Jacobian)", "Observability against the number of poses",
        selected=len(res.calibration.indices) if res.calibration is not None else None,
    )  # fmt: skip


def _plot_singular_value_growth(
    x: list, s_min: list[float], s_max: list[float], path: Path, xlabel: str, ylabel: str,
    title: str, *, selected: int | None = None,
) -> None:  # fmt: skip
    """The smallest and largest singular values against how much of the motion was taken
    (poses selected, or seconds of scans), log scale; a dotted line at ``selected`` poses."""
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.plot(x, s_min, "o-", label="smallest singular value")
    ax.plot(x, s_max, "s--", label="largest singular value", alpha=0.6)
    if selected:
        ax.axvline(selected, color="grey", lw=0.8, ls=":", label=f"{selected} selected")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend(fontsize=8)
    save_figure(fig, path)


def _plot_workspace(res: WorkerResult, path: Path) -> None:
    p = res.params
    poses = res.poses
    tilt, az = _axis_angles(poses.volts, p)
    chosen = np.zeros(len(poses), dtype=bool)
    if res.calibration is not None:
        chosen[res.fit[res.calibration.indices]] = True
    held = np.zeros(len(poses), dtype=bool)
    held[res.held_out] = True
    fig = plt.figure(figsize=(5.5, 5.5))
    ax = fig.add_subplot(projection="polar")
    other = ~chosen & ~held
    scans = res.calibration is not None and res.calibration.selection is None
    ax.scatter(az[other], tilt[other], s=12, color="lightgrey", label="other still poses")
    ax.scatter(az[chosen], tilt[chosen], s=4 if scans else 24, color="tab:blue",
               label="fitted scans" if scans else "selected for the fit")  # fmt: skip
    ax.scatter(az[held], tilt[held], s=6 if scans else 30, marker="x", color="black",
               label="held out of the first fit" if scans else "held out")  # fmt: skip
    A = base_points(p)
    for i in range(4):
        a = np.arctan2(A[i, 1], A[i, 0])
        ax.annotate(f"sensor {i + 1}", (a, 44), ha="center", fontsize=8, color="tab:red")
    ax.set_ylim(0, 45)
    ax.set_title("Where the poses lie: output axis tilt (radius, deg) and direction", fontsize=9)
    ax.legend(loc="lower left", bbox_to_anchor=(-0.1, -0.15), fontsize=8)
    save_figure(fig, path)


def write_report(
    res: WorkerResult, directory: Path, *, progress: Callable[[str], None] = lambda _: None
) -> Path:
    """Write ``directory/index.html`` and its plots; returns the page's path."""
    directory.mkdir(parents=True, exist_ok=True)
    plots = [("changes.png", "Parameter changes")]
    progress("report: plotting the parameter changes")
    _plot_changes(res, directory / "changes.png")
    if res.calibration is not None:
        progress("report: plotting the loop-closure errors")
        _plot_residuals(res, directory / "residuals.png")
        plots.append(("residuals.png", "Loop closure before and after"))
        _plot_singular_values(res, directory / "singular_values.png", progress)
        plots.append(("singular_values.png", "Singular values against poses"))
    progress("report: plotting the workspace")
    _plot_workspace(res, directory / "workspace.png")
    plots.append(("workspace.png", "Poses in the workspace"))
    page = directory / "index.html"
    page.write_text(_html(res, plots), encoding="utf-8")
    return page


def _samples_text(res: WorkerResult) -> str:
    if res.calibration is not None and res.calibration.selection is None:
        return (f"{len(res.poses):,} usable scans, every one fitted ({len(res.held_out):,} "
                "held out of a first fit to check it)")  # fmt: skip
    return f"{len(res.poses)} still poses ({len(res.held_out)} held out)"


def _html(res: WorkerResult, plots: list[tuple[str, str]]) -> str:
    e = html.escape
    verdict = "ACCEPTED" if res.accepted else "REFUSED: " + ", ".join(g.name for g in res.failed)
    color = "#1a7f37" if res.accepted else "#b42318"
    rows = []
    for n in res.model.free:
        i = INDEX[n]
        rows.append(
            f"<tr><td>{n}</td><td>{UNITS[n]}</td><td>{res.previous[i]:.4f}</td>"
            f"<td>{res.params[i]:.4f}</td><td>{res.params[i] - res.previous[i]:+.4f}</td>"
            f"<td>{res.std.get(n, float('nan')):.4f}</td></tr>"
        )
    gates = []
    for g in res.gates:
        value = f"{g.value:.4g}" if isinstance(g.value, float) else str(g.value)
        gates.append(
            f"<tr><td>{'pass' if g.passed else '<b>FAIL</b>'}</td><td>{e(g.name)}</td>"
            f"<td>{e(value)}</td><td>{e(g.limit)}</td><td>{e(g.reason)}</td>"
            f"<td>{e(g.advice)}</td></tr>"
        )
    files = "".join(
        f"<li>{e(str(f.path))}{' (' + e(f.note) + ')' if f.note else ''}</li>"
        for f in res.files
    )
    figs = "".join(
        f'<figure><img src="{name}" alt="{e(title)}"><figcaption>{e(title)}</figcaption></figure>'
        for name, title in plots
    )
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>loopcal calibration report</title>
<style>
body {{ font-family: sans-serif; max-width: 980px; margin: 2em auto; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
td, th {{ border: 1px solid #ccc; padding: 3px 8px; font-size: 14px; }}
.verdict {{ font-size: 22px; font-weight: bold; color: {color}; }}
figure {{ display: inline-block; margin: 8px; }} img {{ max-width: 470px; }}
</style></head><body>
<h1>Calibration report</h1>
<p class="verdict">{e(verdict)}</p>
<p>{res.n_scans:,} scans, {_samples_text(res)};
free parameters: {e(res.model.describe())}; estimator: {e(METHOD_NAMES[res.method])}.
Made {datetime.now(UTC):%Y-%m-%d %H:%M} UTC.</p>
<h2>Parameters</h2>
<table><tr><th>name</th><th>unit</th><th>previous</th><th>new</th><th>change</th>
<th>std</th></tr>{"".join(rows)}</table>
<h2>Acceptance gates</h2>
<table><tr><th></th><th>gate</th><th>value</th><th>limit</th><th>why</th><th>what to do</th>
</tr>{"".join(gates)}</table>
<h2>Plots</h2>{figs}
<h2>Recordings</h2><ul>{files}</ul>
</body></html>
"""
