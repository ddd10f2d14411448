"""Fixtures every test folder may use (the emulated module's fixtures come from loopcal's
own pytest plugin, loopcal.simulator.pytest_plugin: ``ldq412``, ``ldq412_url``, ...)."""

from __future__ import annotations

import pytest

from tests.support.js import mcap_reader


@pytest.fixture(scope="session")
def node_reader() -> list[str]:
    """The command that runs Foxglove's TypeScript MCAP reader (tests/support/js/
    read_mcap.mjs) on a file; fails the test, saying what is missing, without node."""
    return mcap_reader()
