"""``loopcal check --plot`` agrees with its command (issue 32, item 4): the plot is titled by
the verdict the text ends with and the exit status says, its time axis reads for any span
(seconds to days), and the file is the one named (a name without an image format is refused
before any work) and the one printed."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from loopcal.calibration.closure import DriftTest
from loopcal.daemon.inspect.loops import Trace, figure, verdict
from loopcal.simulator.scenarios import HandMoves
from tests.support.processes import fresh_config, loopcal_main
from tests.support.rows import T0
from tests.support.sessions import PAUSE_S, truth_for, write_session


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    """A minute of a technician's session: its loops do not close at a fresh config."""
    d = tmp_path_factory.mktemp("rec")
    truth = truth_for(3)
    write_session(d, HandMoves(3, params=truth, pause_s=PAUSE_S), truth, 60, seed=3)
    return d


def _svg_texts(path: Path) -> list[str]:
    """The texts of an SVG matplotlib wrote (each text element carries its text in a
    comment), in order."""
    return re.findall(r"<!-- (.*?) -->", path.read_text())


@pytest.mark.slow
def test_the_plot_is_titled_by_the_verdict_the_command_prints_and_exits_with(session, tmp_path):
    config = fresh_config(tmp_path / "controller.toml")
    svg = tmp_path / "check.svg"
    proc = loopcal_main("check", session, "--controller-config", config, "--plot", svg)
    assert proc.returncode == 1, proc.stderr
    (said,) = re.findall(r"^Verdict: (.*)\.$", proc.stdout, re.M)
    assert said.startswith("the loops do not close at this config since the recordings began")
    assert proc.stdout.splitlines()[-1] == f"plot: {svg}" and svg.is_file()
    (title,) = [t for t in _svg_texts(svg) if t.startswith("Loop closure at ")]
    assert title == f"Loop closure at controller.toml: {said}", title
    assert "0 change" not in title


def _trace_doc(span_s: float, n: int = 400) -> dict:
    """A check's document whose trace spans ``span_s`` seconds (n tests, nothing moved)."""
    trace = Trace()
    for k, t in enumerate(np.linspace(0, span_s, n)):
        test = DriftTest(np.full(4, 0.01 * k % 0.3), np.full(4, 0.02), np.full(4, 1.0), 0,
                         "step", 0.0, 30, 1.0)  # fmt: skip
        trace.add(T0 + int(t * 1e9), test)
    return {"_trace": trace, "changes": [], "loops_open": None, "loops_close": True,
            "proposals": [], "threshold": 42.178, "false_alarm": 1e-8, "poses": n,
            "config": {"path": "/etc/loopcal/controller.toml"},
            "start_utc": "2026-11-18T11:06:40.000Z", "end_utc": "..."}  # fmt: skip


@pytest.mark.parametrize("span_s", [8.0, 45.0, 20 * 60.0, 5 * 3600.0, 3 * 86400.0, 40 * 86400.0])
def test_the_time_axis_reads_for_any_span(span_s: float) -> None:
    """Each tick of the time axis says another time than its neighbours: 8 s in seconds,
    three days in days (not every tick "the same minute", as %m-%d %H:%M read for a short
    check), the date beside the axis."""
    fig = figure(_trace_doc(span_s))
    fig.canvas.draw()
    ax = fig.axes[-1]
    lo, hi = ax.get_xlim()
    labels = [t.get_text() for t in ax.get_xticklabels() if lo <= t.get_position()[0] <= hi]
    assert len(labels) >= 3 and all(labels), labels
    # the concise labels name the day or month where it turns (12:00, Nov-19, 12:00): no
    # two neighbours alike
    alike = [a for a, b in zip(labels, labels[1:], strict=False) if a == b]
    assert not alike, f"{span_s} s: neighbouring ticks read alike: {labels}"
    assert "2026" in ax.xaxis.get_offset_text().get_text() or any("2026" in x for x in labels)


def test_the_title_is_the_verdict_of_each_outcome() -> None:
    doc = _trace_doc(60.0)
    assert verdict(doc).status == 0 and "the loops close" in verdict(doc).text
    doc["changes"] = [{"sensor": 3, "start_utc": "2026-11-18T11:07:00.000Z"}]
    doc["loops_close"] = False
    doc["proposals"] = [{}]
    found = verdict(doc)
    assert found.status == 1 and found.text == \
        "1 change found (sensor 3); upkeep would propose 1 recalibration"  # fmt: skip
    title = figure(doc).axes[0].get_title()
    assert title.startswith(f"Loop closure at controller.toml: {found.text}"), title


@pytest.mark.parametrize("name", ["check", "check.", "check.jpeg", "plots/"])
def test_a_plot_name_without_an_image_format_is_refused_before_any_work(
    name: str, tmp_path: Path
) -> None:
    """Not 'plot: check' printed and check.png written: refused, exit status 2, nothing
    read (the recording named does not even exist) and nothing written."""
    proc = loopcal_main("check", tmp_path / "missing.mcap", "--controller-config",
                        tmp_path / "missing.toml", "--plot", tmp_path / name)  # fmt: skip
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "loopcal check: error: argument --plot: " in proc.stderr
    assert ".png, .svg, .pdf" in proc.stderr and "missing.mcap" not in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_plot_that_cannot_be_written_is_refused_before_any_work(tmp_path: Path) -> None:
    (tmp_path / "taken.png").mkdir()
    for target, words in ((tmp_path / "no-such-dir" / "check.png", "does not exist"),
                          (tmp_path / "taken.png", "is a directory")):  # fmt: skip
        proc = loopcal_main("check", tmp_path / "missing.mcap", "--controller-config",
                            tmp_path / "missing.toml", "--plot", target)  # fmt: skip
        assert proc.returncode == 2 and words in proc.stderr, proc.stderr
        assert proc.stderr.startswith(f"loopcal check: error: --plot {target}: "), proc.stderr
