"""The HTML report and ``loopcal check --plot`` looked at as a person would: headless
Chromium (Debian's package; .ci/run installs it) opens them, every image must load and the
verdict must be visible."""

from __future__ import annotations

import json
import shutil
import subprocess

import pytest

from loopcal.simulator.scenarios import HandMoves
from tests.support.js import JS, npm_installed
from tests.support.processes import fresh_config, loopcal
from tests.support.sessions import PAUSE_S, truth_for, write_session

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        pytest.fail("chromium is missing: .ci/run installs Debian's chromium package")
    return path


def view(*urls: str, text: str | None = None) -> list[dict]:
    node = npm_installed()
    cmd = [node, str(JS / "view_page.mjs"), *urls] + (["--text", text] if text else [])
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120,
                          env={"CHROMIUM": chromium(), "PATH": "/usr/bin:/bin"})  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return [json.loads(line) for line in proc.stdout.splitlines()]


def test_the_report_and_the_check_plot_show_in_a_browser(tmp_path):
    truth = truth_for(4)
    write_session(tmp_path / "rec", HandMoves(4, params=truth, pause_s=PAUSE_S), truth, 120,
                  seed=4)  # fmt: skip
    config = fresh_config(tmp_path / "controller.toml")
    proc = loopcal("calibrate", tmp_path / "rec", "--controller-config", config,
                   "--report", tmp_path / "report")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    plot = tmp_path / "check.png"
    loopcal("check", tmp_path / "rec", "--controller-config", config, "--plot", plot)
    [report] = view((tmp_path / "report" / "index.html").as_uri(), text=".verdict")
    assert report["ok"] and report["visible"] and report["text"] == "ACCEPTED"
    assert len(report["images"]) == 4
    assert all(i["loaded"] and i["width"] > 300 for i in report["images"]), report["images"]
    [png] = view(plot.as_uri())
    assert png["ok"] and png["images"][0]["loaded"] and png["images"][0]["width"] > 800
