"""loopcal as it is installed: one import package, ``loopcal``, that installs beside anything.

The repository's folders (calibration/, drivers/, simulator/, daemon/) become
``loopcal.calibration`` ... through pyproject.toml's package-dir; these tests build the real
wheel and sdist, install the wheel into a fresh virtual environment beside python-daemon
(whose top-level package is ``daemon``), and run a foreign project that has its own
``simulator``, ``drivers`` and ``daemon`` packages with our pytest plugin active.
"""

from __future__ import annotations

import os
import site
import subprocess
import sys
import tarfile
import tomllib
import venv
import zipfile
from pathlib import Path

import pytest

from tests.support import ROOT

pytest_plugins = ("pytester",)

CODE = ("calibration", "drivers", "simulator", "daemon")


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_every_code_folder_is_a_listed_package_under_loopcal() -> None:
    setuptools = _pyproject()["tool"]["setuptools"]
    folders = {
        "loopcal." + ".".join(init.parent.relative_to(ROOT).parts)
        for name in CODE for init in (ROOT / name).rglob("__init__.py")
    }  # fmt: skip
    listed = set(setuptools["packages"])
    assert folders <= listed, f"not listed in pyproject.toml: {sorted(folders - listed)}"
    assert listed - folders == {"loopcal.systemd", "loopcal.docs"}
    assert all(setuptools["package-dir"][f"loopcal.{name}"] == name for name in CODE)
    assert setuptools["package-dir"]["loopcal.docs"] == "docs"


def test_metadata_a_distribution_tool_reads() -> None:
    project = _pyproject()["project"]
    assert project["license"] == "MIT"  # an SPDX expression, not the deprecated table
    assert "urls" not in project  # none is true yet: no page it would name exists
    assert project["scripts"]["loopcal"] == "loopcal.daemon.cli:main"
    assert project["entry-points"]["pytest11"]["ldq412"] == "loopcal.simulator.pytest_plugin"


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The wheel and the sdist, built from this checkout with the test environment's own
    setuptools (no build isolation: nothing downloaded)."""
    out = tmp_path_factory.mktemp("dist")
    proc = subprocess.run(
        [sys.executable, "-m", "build", "--no-isolation", "--outdir", str(out), str(ROOT)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    (wheel,) = out.glob("loopcal-*.whl")
    (sdist,) = out.glob("loopcal-*.tar.gz")
    return wheel, sdist


@pytest.mark.slow
def test_the_wheel_holds_one_top_level_package_and_its_data(built: tuple[Path, Path]) -> None:
    wheel, _ = built
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names}
    assert top == {"loopcal", next(t for t in top if t.endswith(".dist-info"))}, top
    assert "loopcal/__init__.py" not in names  # a namespace package: nothing to collide with
    for needed in (
        "loopcal/daemon/cli.py",
        "loopcal/simulator/pytest_plugin.py",
        "loopcal/systemd/loopcal.service",
        "loopcal/systemd/loopcal-calibrate.service",
        "loopcal/systemd/sysusers.d/loopcal.conf",
        "loopcal/systemd/tmpfiles.d/loopcal.conf",
        "loopcal/systemd/README.md",
        "loopcal/docs/foxglove/loopcal-layout.json",
        "loopcal/docs/daemon.md",
    ):
        assert needed in names, needed  # fmt: skip
    # the API reference's sources are not package data (pyproject.toml's exclude-package-data)
    assert not [n for n in names if n.startswith("loopcal/docs/api/")]
    meta = next(n for n in names if n.endswith(".dist-info/METADATA"))
    text = zipfile.ZipFile(wheel).read(meta).decode()
    assert "License-Expression: MIT" in text
    assert "Project-URL:" not in text
    entry = zipfile.ZipFile(wheel).read(meta.replace("METADATA", "entry_points.txt")).decode()
    assert "loopcal = loopcal.daemon.cli:main" in entry
    assert "ldq412 = loopcal.simulator.pytest_plugin" in entry


@pytest.mark.slow
def test_the_sdist_holds_every_tracked_file(built: tuple[Path, Path]) -> None:
    """What the tests and the docs need comes with the sdist: every file git tracks."""
    _, sdist = built
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True)
    if tracked.returncode != 0:
        pytest.skip("not a git checkout")
    with tarfile.open(sdist) as tar:
        inside = {m.name.split("/", 1)[1] for m in tar.getmembers() if "/" in m.name}
    missing = [f for f in tracked.stdout.split() if (ROOT / f).exists() and f not in inside]
    assert not missing, missing[:20]


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=600, **kw)


@pytest.mark.slow
def test_the_wheel_installs_beside_python_daemon(built: tuple[Path, Path],
                                                  tmp_path: Path) -> None:  # fmt: skip
    """python-daemon's ``daemon`` and loopcal's ``loopcal.daemon`` side by side in a fresh
    venv; uninstalling python-daemon leaves loopcal whole."""
    wheel, _ = built
    env_dir = tmp_path / "fresh"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py, loopcal = env_dir / "bin" / "python", env_dir / "bin" / "loopcal"
    env = {k: v for k, v in os.environ.items() if k not in {"PYTHONPATH", "VIRTUAL_ENV"}}
    # loopcal's dependencies from the test environment's site-packages, put on the fresh
    # venv's path (a .pth line runs no .pth of that folder: the checkout's editable loopcal
    # stays out): unpacking scipy and numpy again was most of this test's CPU, and the
    # wheel's own files are what it is about. The wheel's requirements still have to be
    # met there, or pip refuses it.
    (fresh_site,) = (env_dir / "lib").glob("python3*/site-packages")
    (fresh_site / "test-environment.pth").write_text(
        "\n".join(site.getsitepackages()) + "\n", encoding="utf-8"
    )
    pip = _run([str(py), "-m", "pip", "install", "-q", "--disable-pip-version-check",
                "--no-compile", str(wheel), "python-daemon"], env=env, cwd=tmp_path)  # fmt: skip
    assert pip.returncode == 0, pip.stderr[-3000:]
    check = ("import daemon, loopcal.daemon.cli, loopcal.drivers, loopcal.simulator; "
             "from daemon import DaemonContext; "
             "assert 'site-packages' in daemon.__file__ and 'loopcal' not in daemon.__file__; "
             "print(loopcal.daemon.cli.__file__)")  # fmt: skip
    proc = _run([str(py), "-c", check], env=env, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert str(env_dir) in proc.stdout
    version = _run([str(loopcal), "--version"], env=env, cwd=tmp_path)
    assert version.returncode == 0 and version.stdout.startswith("loopcal "), version.stderr
    # the package data is where `loopcal files` says, inside the fresh venv
    files = _run([str(loopcal), "files", "systemd/loopcal.service",
                  "docs/foxglove/loopcal-layout.json"], env=env, cwd=tmp_path)  # fmt: skip
    assert files.returncode == 0, files.stderr
    for line in files.stdout.split():
        assert Path(line).is_file() and str(env_dir) in line, line
    root = tmp_path / "root"
    root.mkdir()
    units = _run([str(loopcal), "install-units", str(root)], env=env, cwd=tmp_path)
    assert units.returncode == 0, units.stderr
    assert (root / "etc/systemd/system/loopcal.service").read_bytes() == \
        (ROOT / "systemd/loopcal.service").read_bytes()  # fmt: skip
    assert (root / "etc/sysusers.d/loopcal.conf").is_file()
    assert (root / "etc/tmpfiles.d/loopcal.conf").is_file()
    gone = _run([str(py), "-m", "pip", "uninstall", "-y", "-q", "python-daemon"], env=env)
    assert gone.returncode == 0, gone.stderr
    after = _run([str(py), "-c", "import loopcal.daemon.cli, loopcal.daemon.recording"],
                 env=env, cwd=tmp_path)  # fmt: skip
    assert after.returncode == 0, after.stderr
    assert _run([str(loopcal), "--version"], env=env, cwd=tmp_path).returncode == 0
    missing = _run([str(py), "-c", "import daemon"], env=env, cwd=tmp_path)
    assert missing.returncode != 0  # python-daemon's package really went, ours did not


FOREIGN_TEST = """
import daemon
import drivers
import simulator

from loopcal.drivers import open_daq


def test_its_own_packages_are_its_own():
    assert (daemon.WHOSE, drivers.WHOSE, simulator.WHOSE) == ("theirs",) * 3


def test_the_plugin_serves_a_module(ldq412):
    with open_daq(ldq412.url) as daq:
        assert daq.identity is not None
    assert simulator.WHOSE == "theirs"
"""


@pytest.mark.slow
def test_a_project_with_its_own_simulator_drivers_daemon_runs_with_our_plugin(
    pytester: pytest.Pytester,
) -> None:
    for name in ("simulator", "drivers", "daemon"):
        pytester.mkpydir(name).joinpath("__init__.py").write_text('WHOSE = "theirs"\n')
    pytester.makepyfile(test_foreign=FOREIGN_TEST)
    result = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    result.stdout.fnmatch_lines(["plugins:*loopcal-*"])
    result.assert_outcomes(passed=2)
