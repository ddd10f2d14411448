"""Fixtures of the driver tests."""

from __future__ import annotations

import pytest

from tests.support.drivers import emulator_factory


@pytest.fixture
def emu_factory():
    """``make(transport, timeout=..., **emulator_options) -> (emulator, daq, clock)``:
    started emulators with an open driver each, closed after the test."""
    yield from emulator_factory()
