"""The driver registry against real installed distributions: a package beside loopcal adds
a URL scheme by an entry point of the group ``loopcal.drivers``, without editing loopcal.

Each test writes tiny packages and their ``*.dist-info`` (METADATA, entry_points.txt) into
a temporary directory, the way pip installs them, and runs a Python with that directory on
its path: importlib.metadata finds them as it finds any installed package. Nothing is
mocked, and this process's registry is left alone.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

#: a third party's transport: a module that is not there (its scans never come), enough
#: for open_daq to hand it a parsed URL and for its own URL parameters to be checked
VIRTUAL = '''
from typing import ClassVar

from loopcal.drivers import DAQ, DAQDisconnected, Identity, ldq412


class VirtualDAQ(DAQ):
    """A module that is not there."""

    url_params: ClassVar[frozenset[str]] = frozenset({"rate"})

    @classmethod
    def url_options(cls, url):
        return {"name": url.host, "rate": url.get_int("rate", 20, lo=1, hi=200)}

    def __init__(self, name, rate, *, timeout, check_identity):
        self.url = f"{self.scheme}://{name}?rate={rate}"
        self.identity = Identity(ldq412.MODEL_NAME, "1.00", 1, ldq412.MODEL_CODE)
        self._rate, self._pending, self._closed = rate, [], False

    def read_scans(self):
        if self._closed:
            raise DAQDisconnected(f"{self.url}: closed")
        return []

    def snapshot(self):
        raise DAQDisconnected(f"{self.url}: a virtual module makes no scans")

    def read_scan_rate(self):
        return self._rate

    def _write_scan_rate(self, hz):
        self._rate = hz

    def clear_restart(self):
        return False

    def close(self):
        self._closed = True
'''


#: a subclass that says its scheme is another than its entry point's name
RENAMED = """

class Renamed(VirtualDAQ):
    scheme = "other"
"""


def install(root: Path, name: str, entry_points: dict[str, str], modules: dict[str, str]) -> None:
    """Write a distribution ``name`` 1.0 into ``root`` as pip would: its modules, and a
    dist-info declaring ``entry_points`` (scheme -> ``"module:object"``) in loopcal's group."""
    for module, source in modules.items():
        (root / f"{module}.py").write_text(textwrap.dedent(source))
    info = root / f"{name.replace('-', '_')}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    lines = "".join(f"{scheme} = {target}\n" for scheme, target in entry_points.items())
    (info / "entry_points.txt").write_text(f"[loopcal.drivers]\n{lines}")


def run(root: Path, code: str) -> dict:
    """Run ``code`` in a Python with ``root`` on its path; what it prints, as JSON."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    proc = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        env=env, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def error_of(root: Path, url: str, *, before: str = "") -> dict:
    """The error ``driver_for_url(url)`` raises in a Python with ``root`` on its path."""
    return run(
        root,
        textwrap.dedent(before)
        + textwrap.dedent(f"""
        import json
        from loopcal.drivers import DriverLoadError, driver_for_url
        try:
            driver_for_url({url!r})
        except Exception as exc:
            print(json.dumps({{"type": type(exc).__name__, "message": str(exc),
                              "value_error": isinstance(exc, ValueError),
                              "load_error": isinstance(exc, DriverLoadError)}}))
        else:
            print(json.dumps(None))
    """),
    )


def test_a_package_installed_beside_loopcal_adds_a_scheme(tmp_path: Path) -> None:
    install(tmp_path, "loopcal-virtual", {"virtual": "loopcal_virtual:VirtualDAQ"},
            {"loopcal_virtual": VIRTUAL})  # fmt: skip
    got = run(
        tmp_path,
        """
        import json, sys
        from loopcal.drivers import driver_for_url, open_daq
        from loopcal.drivers.registry import registered_schemes
        driver_for_url("ascii:///dev/ttyUSB0?addr=01")
        loaded_early = "loopcal_virtual" in sys.modules  # a driver loads when asked for
        with open_daq("virtual://bench?rate=50") as daq:
            opened = [type(daq).__module__, type(daq).__name__, daq.scheme, daq.url,
                      daq.read_scans()]
        try:
            driver_for_url("virtual://bench?baud=9600")
        except ValueError as exc:
            its_params = str(exc)
        try:
            driver_for_url("nope://x")
        except ValueError as exc:
            unknown = str(exc)
        print(json.dumps({"loaded_early": loaded_early, "opened": opened,
                          "its_params": its_params, "unknown": unknown,
                          "schemes": sorted(registered_schemes())}))
    """,
    )
    assert not got["loaded_early"]
    assert got["opened"] == ["loopcal_virtual", "VirtualDAQ", "virtual",
                             "virtual://bench?rate=50", []]  # fmt: skip
    assert got["its_params"] == (
        "virtual://bench?baud=9600: unknown parameter(s) ['baud'] for virtual (allowed: ['rate'])"
    )
    assert got["unknown"] == (
        "unknown DAQ URL scheme 'nope' (known: ascii, modbus-rtu, modbus-tcp, virtual)"
    )
    assert got["schemes"] == ["ascii", "modbus-rtu", "modbus-tcp", "virtual"]


@pytest.mark.slow
def test_a_scheme_claimed_by_two_packages_names_both(tmp_path: Path) -> None:
    install(tmp_path, "loopcal-virtual", {"virtual": "loopcal_virtual:VirtualDAQ"},
            {"loopcal_virtual": VIRTUAL})  # fmt: skip
    install(tmp_path, "other-virtual", {"virtual": "other_virtual:VirtualDAQ",
                                        "modbus-tcp": "other_virtual:VirtualDAQ"},
            {"other_virtual": VIRTUAL})  # fmt: skip
    err = error_of(tmp_path, "virtual://bench")
    assert err["load_error"] and err["value_error"]  # a settings check reports it on the URL
    assert err["message"] == (
        "URL scheme 'virtual' is claimed more than once: loopcal_virtual:VirtualDAQ by package "
        "loopcal-virtual 1.0; other_virtual:VirtualDAQ by package other-virtual 1.0 "
        "(uninstall one of the packages, or rename its scheme)"
    )
    err = error_of(tmp_path, "modbus-tcp://127.0.0.1:502")
    assert err["load_error"]
    assert "loopcal.drivers.modbus_tcp:ModbusTcpDAQ by package loopcal " in err["message"]
    assert "other_virtual:VirtualDAQ by package other-virtual 1.0" in err["message"]
    assert error_of(tmp_path, "ascii:///dev/ttyUSB0?addr=01") is None  # the others unharmed


@pytest.mark.slow
def test_a_driver_that_fails_to_load_names_its_package(tmp_path: Path) -> None:
    install(tmp_path, "broken-drivers", {"broken": "broken_driver:VirtualDAQ",
                                         "absent": "virtual_driver:NoSuchDAQ",
                                         "notdaq": "virtual_driver:ClassVar",
                                         "renamed": "virtual_driver:Renamed"},
            {"broken_driver": 'raise ImportError("needs libvirtualdaq.so")\n',
             "virtual_driver": VIRTUAL + RENAMED})  # fmt: skip
    err = error_of(tmp_path, "broken://x")
    assert err["load_error"] and err["value_error"]
    assert err["message"] == (
        "the driver for broken:// cannot be loaded: entry point broken = "
        "broken_driver:VirtualDAQ of package broken-drivers 1.0 (group loopcal.drivers): "
        "ImportError: needs libvirtualdaq.so"
    )
    err = error_of(tmp_path, "absent://x")
    assert err["load_error"] and "package broken-drivers 1.0" in err["message"]
    assert "AttributeError" in err["message"] and "NoSuchDAQ" in err["message"]
    err = error_of(tmp_path, "notdaq://x")
    assert err["load_error"] and err["message"] == (
        "entry point notdaq = virtual_driver:ClassVar of package broken-drivers 1.0 (group "
        "loopcal.drivers) names typing.ClassVar, not a subclass of loopcal's DAQ"
    )
    err = error_of(tmp_path, "renamed://x")
    assert err["load_error"] and err["message"] == (
        "entry point renamed = virtual_driver:Renamed of package broken-drivers 1.0 (group "
        "loopcal.drivers) names a class whose scheme is 'other'"
    )


def test_a_program_registering_a_packages_scheme_is_told_whose_it_is(tmp_path: Path) -> None:
    install(tmp_path, "loopcal-virtual", {"virtual": "loopcal_virtual:VirtualDAQ"},
            {"loopcal_virtual": VIRTUAL})  # fmt: skip
    before = """
        from loopcal.drivers import register_scheme
        from loopcal_virtual import VirtualDAQ

        @register_scheme("virtual")
        class Mine(VirtualDAQ):
            pass
    """
    err = error_of(tmp_path, "virtual://bench", before=before)
    assert err["load_error"] and err["message"] == (
        "URL scheme 'virtual' is claimed more than once: loopcal_virtual:VirtualDAQ by package "
        "loopcal-virtual 1.0; __main__:Mine by register_scheme (uninstall one of the "
        "packages, or rename its scheme)"
    )
