"""Fixtures every test folder may use (the emulated module's fixtures come from loopcal's
own pytest plugin, loopcal.simulator.pytest_plugin: ``ldq412``, ``ldq412_url``, ...)."""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support import fuzz
from tests.support.js import mcap_reader
from tests.support.workers import SharedFixtureScheduling

fuzz.register()  # Hypothesis's profiles, ci loaded: --hypothesis-profile=dev|deep (fuzz.py)


def pytest_xdist_make_scheduler(config, log):
    """``-n N`` (xdist's ``--dist load``): each test to whichever worker is free, but a
    file that makes a fixture once goes to one worker (tests/support/workers.py). Another
    ``--dist`` given is xdist's own."""
    if config.getvalue("dist") == "load":
        return SharedFixtureScheduling(config, log)
    return None


@pytest.fixture(scope="session")
def node_reader() -> list[str]:
    """The command that runs Foxglove's TypeScript MCAP reader (tests/support/js/
    read_mcap.mjs) on a file; fails the test, saying what is missing, without node."""
    return mcap_reader()


@pytest.fixture(autouse=True)
def runtime_directory(monkeypatch) -> Iterator[Path]:
    """Each test its own runtime directory (``$LOOPCAL_RUNTIME_DIR``: the modules' lock
    files, the daemon's control socket), inherited by the loopcal subprocesses it starts:
    tests on two workers that open the same address (an unreachable one, say) never take
    each other's module locks. Short, as a unix socket's path must be (108 bytes)."""
    path = Path(tempfile.mkdtemp(prefix="lc-run-"))
    monkeypatch.setenv("LOOPCAL_RUNTIME_DIR", str(path))
    yield path
    shutil.rmtree(path, ignore_errors=True)
