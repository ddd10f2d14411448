"""The pytest plugin (simulator/pytest_plugin.py) as another project meets it: pytest run
in a subprocess, in a directory that is not this project, finding the plugin by its
``pytest11`` entry point alone (no conftest, no import of ours in the collected files'
set-up)."""

from __future__ import annotations

import re

import pytest

from tests.support import ROOT

pytestmark = pytest.mark.slow  # docs/architecture.md, "The fast loop"

pytest_plugins = ("pytester",)


def _docs_example() -> str:
    """The complete example test of docs/testing.md (its first python block)."""
    text = (ROOT / "docs" / "testing.md").read_text(encoding="utf-8")
    m = re.search(r"```python\n(.*?)```", text, re.S)
    assert m, "docs/testing.md has no python example"
    return m.group(1)


def test_the_documented_example_passes_in_a_foreign_project(pytester: pytest.Pytester) -> None:
    assert not (pytester.path / "pyproject.toml").exists()
    assert ROOT not in pytester.path.parents
    pytester.makepyfile(test_controller_io=_docs_example())
    result = pytester.runpytest_subprocess("-v", "-p", "no:cacheprovider")
    result.stdout.fnmatch_lines(["plugins:*loopcal-*"])
    result.assert_outcomes(passed=7)


def test_options_come_from_cli_marker_and_param_in_that_order(
    pytester: pytest.Pytester,
) -> None:
    pytester.makepyfile(
        """
        import pytest

        def test_cli_default(ldq412):
            assert ldq412.transport == "ascii"
            assert ldq412.url.startswith("ascii:///dev/pts/")

        @pytest.mark.ldq412(transport="modbus-rtu", seed=4, scan_rate_hz=50, clock="manual")
        def test_marker_wins_over_cli(ldq412):
            assert ldq412.url.startswith("modbus-rtu:///dev/pts/")
            assert ldq412.options.seed == 4
            scans = ldq412.wait_scans(50)
            assert scans[-1].time_us - scans[0].time_us == 49 * 20_000

        @pytest.mark.ldq412(transport="ascii", seed=9)
        @pytest.mark.parametrize(
            "ldq412", ["modbus-tcp", {"transport": "modbus-tcp", "seed": 2}], indirect=True
        )
        def test_param_wins_over_marker(ldq412):
            assert ldq412.url.startswith("modbus-tcp://127.0.0.1:")
            assert ldq412.options.seed in (9, 2)

        @pytest.mark.ldq412(truth={"d03": 99.125}, offset_error_mm=0.0)
        def test_truth_override(ldq412, ldq412_factory):
            assert ldq412.truth.as_dict()["d03"] == 99.125
            other = ldq412_factory(seed=1)
            assert other.truth.as_dict()["d03"] == 99.125  # the marker's options are defaults
            assert other.url != ldq412.url
        """
    )
    result = pytester.runpytest_subprocess("--ldq412-transport", "ascii", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=5)


def test_bad_options_fail_setup_naming_the_option(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import pytest

        @pytest.mark.ldq412(sped=10)
        def test_typo(ldq412):
            pass

        @pytest.mark.ldq412(transport="can")
        def test_bad_transport(ldq412):
            pass

        @pytest.mark.ldq412(clock="manual", speed=5)
        def test_manual_and_fast(ldq412):
            pass

        @pytest.mark.ldq412(truth={"d09": 1.0})
        def test_unknown_parameter(ldq412):
            pass
        """
    )
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(errors=4)
    result.stdout.fnmatch_lines(
        [
            "*unknown ldq412 option(s) 'sped'; the options are *",
            "*ldq412 option transport='can': one of modbus-tcp, modbus-rtu, ascii*",
            "*ldq412 option speed: a manual clock moves only when advanced*",
            "*unknown parameter(s) 'd09'*",
        ],
        consecutive=False,
    )


def test_modules_are_closed_after_each_test_even_a_failing_one(
    pytester: pytest.Pytester,
) -> None:
    """The first test fails holding a TCP module and an ASCII pty; the second finds the
    port refused and the pseudo-terminal gone."""
    pytester.makepyfile(
        """
        import os, socket
        import pytest

        held = {}

        def test_fails_holding_modules(ldq412, ldq412_factory):
            held["port"] = ldq412.port
            held["ascii"] = ldq412_factory(transport="ascii")
            held["pty"] = held["ascii"].port
            with socket.create_connection(("127.0.0.1", held["port"]), timeout=1):
                pass
            assert os.path.exists(held["pty"])
            assert False, "on purpose"

        def test_then_everything_is_closed():
            with pytest.raises(ConnectionRefusedError):
                socket.create_connection(("127.0.0.1", held["port"]), timeout=1)
            assert not held["ascii"].emulator.running
            assert not os.path.exists(held["pty"])  # the pseudo-terminal is gone
        """
    )
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(passed=1, failed=1)
    result.stdout.fnmatch_lines(["*AssertionError: on purpose*"])


def test_the_plugin_costs_no_emulator_import_until_used(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(
        """
        import sys

        def test_nothing_heavy_loaded():
            assert "loopcal.simulator.pytest_plugin" in sys.modules
            assert "loopcal.simulator.emulator" not in sys.modules
            assert "pymodbus" not in sys.modules
        """
    )
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.assert_outcomes(passed=1)
