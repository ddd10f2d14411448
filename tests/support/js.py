"""Node.js for the tests that check our outputs with the tools their users use (Foxglove's
TypeScript MCAP reader; headless Chromium through playwright-core): tests/support/js/."""

from __future__ import annotations

import fcntl
import json
import shutil
import subprocess
from pathlib import Path

import pytest

JS = Path(__file__).parent / "js"


def npm_installed() -> str:
    """The path of node, with tests/support/js's packages installed (``npm ci`` the first time);
    fails the test, saying what is missing, if node or npm is."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.fail(
            "node and npm are required: recordings are checked with Foxglove's TypeScript MCAP "
            "reader and pages in Chromium (install Node.js 20 or newer with npm; .ci/run does)"
        )
    # one install at a time: the suite's workers (pytest-xdist) share this folder
    with open(JS / ".npm-ci.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        wanted = json.loads((JS / "package.json").read_text())["dependencies"]
        if not all((JS / "node_modules" / name).is_dir() for name in wanted):
            try:
                subprocess.run([npm, "ci", "--no-audit", "--no-fund"], cwd=JS, check=True,
                               timeout=300, capture_output=True, text=True)  # fmt: skip
            except subprocess.CalledProcessError as exc:
                pytest.fail(f"npm ci in {JS} failed:\n{exc.stdout}\n{exc.stderr}")
            except subprocess.TimeoutExpired:
                pytest.fail(f"npm ci in {JS} took more than 300 s")
    return node


def mcap_reader() -> list[str]:
    """The command that runs read_mcap.mjs (Foxglove's TypeScript MCAP reader) on a file."""
    return [npm_installed(), str(JS / "read_mcap.mjs")]


def run_node(node_reader: list[str], path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*node_reader, str(path)], capture_output=True, text=True, timeout=60)


def read_ts(node_reader: list[str], path: Path) -> dict:
    """What read_mcap.mjs read of the file at ``path`` (it must succeed)."""
    proc = run_node(node_reader, path)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def watch_live(port: int, seconds: float, clients: int = 1, stalled: int = 0) -> dict:
    """What Foxglove's WebSocket protocol client (@foxglove/ws-protocol under node) saw of a
    live view on ``port`` in ``seconds``: its channels, and per topic what it received and
    decoded (js/live_client.mjs)."""
    proc = subprocess.run(
        [npm_installed(), str(JS / "live_client.mjs"), f"ws://127.0.0.1:{port}", str(seconds),
         str(clients), str(stalled)],
        capture_output=True, text=True, timeout=seconds + 60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)
