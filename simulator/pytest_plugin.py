"""pytest plugin: an emulated LDQ-412 on a real transport, per test (docs/testing.md).

Installing loopcal registers it (the ``pytest11`` entry point ``ldq412``); a project that
talks to the module needs nothing else::

    from loopcal.drivers import open_daq

    @pytest.mark.ldq412(scenario="static", seed=7)
    def test_reads(ldq412):
        with open_daq(ldq412.url) as daq:
            ...
        ldq412.power_cycle()

    @pytest.mark.parametrize("ldq412", ["modbus-tcp", "modbus-rtu", "ascii"], indirect=True)
    def test_every_transport(ldq412): ...

    @pytest.mark.ldq412(scenario="task", task_waypoints=4, task_move_s=1.5, task_dwell_s=0)
    def test_in_operation(ldq412): ...  # the controller's task loop, for ever

    def test_two_modules(ldq412_factory):
        a, b = ldq412_factory(seed=1), ldq412_factory(transport="ascii", seed=2)

Fixtures:

- ``ldq412``: an :class:`~loopcal.simulator.testing.EmulatedLDQ412` started for the test and
  closed after it. Its options, later ones winning: the defaults, ``--ldq412-transport``
  on the command line, the closest ``@pytest.mark.ldq412(**options)``, and an indirect
  parameter (a transport name or a dict of options).
- ``ldq412_factory``: ``make(**options)`` builds as many modules as a test wants (marker
  options as defaults), all closed after it.

Options are the fields of :class:`~loopcal.simulator.testing.LDQ412Options`; an unknown one fails
the test's setup with a message naming it. Importing this module costs nothing until a
fixture is used (the emulator is imported then).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import pytest

from .choices import TRANSPORTS

if TYPE_CHECKING:
    from .testing import EmulatedLDQ412

_MARKER = (
    "ldq412(**options): options of the emulated LDQ-412 the ldq412 fixtures serve "
    "(transport, scan_rate_hz, speed, clock, seed, scenario, pause_s, task_waypoints, "
    "task_move_s, task_dwell_s, noise_volts, offset_error_mm, truth, open_points, unit, "
    "ascii_addr, ascii_checksum, line)"
)


def pytest_addoption(parser: pytest.Parser) -> None:
    """pytest hook: add ``--ldq412-transport`` (the ``ldq412`` fixtures' default transport).

    Parameters
    ----------
    parser : pytest.Parser
        pytest's command-line parser.
    """
    group = parser.getgroup("ldq412", "emulated LDQ-412 DAQ module (loopcal)")
    group.addoption(
        "--ldq412-transport",
        choices=TRANSPORTS,
        default=None,
        help="transport of the ldq412 fixture where a test does not choose one "
        "(default modbus-tcp)",
    )


def pytest_configure(config: pytest.Config) -> None:
    """pytest hook: register the ``ldq412`` marker (``pytest --markers`` lists it).

    Parameters
    ----------
    config : pytest.Config
        pytest's configuration.
    """
    config.addinivalue_line("markers", _MARKER)


def _options(request: pytest.FixtureRequest) -> dict[str, Any]:
    """Options from the command line and the closest marker (later ones win)."""
    options: dict[str, Any] = {}
    transport = request.config.getoption("ldq412_transport", default=None)
    if transport:
        options["transport"] = transport
    marker = request.node.get_closest_marker("ldq412")
    if marker is not None:
        if marker.args:
            raise pytest.UsageError(
                f"@pytest.mark.ldq412 takes keyword options only, got {marker.args!r} "
                "(e.g. @pytest.mark.ldq412(transport='ascii'))"
            )
        options.update(marker.kwargs)
    return options


def _make(options: dict[str, Any]) -> EmulatedLDQ412:
    from .testing import EmulatedLDQ412, LDQ412Options

    return EmulatedLDQ412(LDQ412Options.from_mapping(options))


@pytest.fixture
def ldq412_factory(request: pytest.FixtureRequest) -> Iterator[Callable[..., EmulatedLDQ412]]:
    """``make(**options)``: a started emulated module per call, closed after the test.

    The closest ``@pytest.mark.ldq412(**options)`` (and ``--ldq412-transport``) give the
    defaults; the call's keywords win.

    Parameters
    ----------
    request : pytest.FixtureRequest
        pytest's request (the test's marker and the command line).

    Yields
    ------
    callable
        ``make(**options) -> EmulatedLDQ412``, the options being
        :class:`~loopcal.simulator.testing.LDQ412Options` fields. Every module made is
        closed after the test (the first error closing one is raised once all are
        closed).
    """
    defaults = _options(request)
    made: list[EmulatedLDQ412] = []

    def make(**options: Any) -> EmulatedLDQ412:
        module = _make({**defaults, **options})
        made.append(module)
        return module

    yield make
    errors = []
    for module in reversed(made):
        try:
            module.close()
        except Exception as exc:  # close the others; report after
            errors.append(exc)
    if errors:
        raise errors[0]


@pytest.fixture
def ldq412(request: pytest.FixtureRequest) -> Iterator[EmulatedLDQ412]:
    """An emulated LDQ-412 started for the test and closed after it (``.url``).

    Its options, later ones winning: the defaults, ``--ldq412-transport``, the closest
    ``@pytest.mark.ldq412(**options)``, and an indirect parameter (a transport name or a
    dict of options).

    Parameters
    ----------
    request : pytest.FixtureRequest
        pytest's request (the marker, the command line, the indirect parameter).

    Yields
    ------
    EmulatedLDQ412
        The started module (:class:`~loopcal.simulator.testing.EmulatedLDQ412`), closed
        after the test even when it fails.

    Raises
    ------
    pytest.UsageError
        If the marker has positional arguments, or the indirect parameter is neither a
        transport name nor a dict.
    TypeError
        If an option is unknown (the test's setup fails, naming it).
    ValueError
        If an option's value is refused.
    """
    options = _options(request)
    param = getattr(request, "param", None)
    if isinstance(param, str):
        options["transport"] = param
    elif isinstance(param, dict):
        options.update(param)
    elif param is not None:
        raise pytest.UsageError(
            f"an indirect ldq412 parameter is a transport name or a dict of options, got {param!r}"
        )
    module = _make(options)
    try:
        yield module
    finally:
        module.close()
