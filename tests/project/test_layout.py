"""The tests' and bench scripts' own layout: a folder of tests per package, what they share
in tests/support/ (never imported from a test module), bench scripts that run as modules
from the repository's root without touching sys.path."""

from __future__ import annotations

import ast
import subprocess
import sys

import pytest

from tests.support import ROOT

TESTS = ROOT / "tests"
BENCH = ROOT / "bench"
SCRIPTS = sorted(p.stem for p in BENCH.glob("*.py") if not p.stem.startswith("_"))


def imported_modules(path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_every_package_of_the_code_has_its_folder_of_tests():
    for name in ("calibration", "drivers", "simulator", "daemon", "systemd"):
        assert list((TESTS / name).glob("test_*.py")), f"tests/{name}/ has no tests"
    for sub in (ROOT / "daemon").iterdir():
        if (sub / "__init__.py").is_file() and sub.name != "inspect":  # inspect: commands/
            assert (TESTS / "daemon" / sub.name).is_dir(), f"no tests/daemon/{sub.name}/"
    assert not list(TESTS.glob("test_*.py")), "a test module at the top of tests/"


def test_every_folder_of_tests_is_a_package():
    """Test modules of one name in two folders (test_ascii.py) need packages to coexist."""
    for path in TESTS.rglob("test_*.py"):
        for parent in path.relative_to(TESTS).parents:
            folder = TESTS / parent
            assert (folder / "__init__.py").is_file(), f"{folder} has no __init__.py"


@pytest.mark.slow
def test_no_test_module_imports_another_and_no_helper_lies_outside_support():
    for path in TESTS.rglob("*.py"):
        rel = path.relative_to(ROOT)
        if "support" not in rel.parts and path.name not in ("__init__.py", "conftest.py"):
            assert path.name.startswith("test_"), f"{rel}: helpers belong in tests/support/"
        for module in imported_modules(path):
            last = module.rsplit(".", 1)[-1]
            assert not last.startswith("test_"), f"{rel} imports the test module {module}"
            assert not module.endswith("_helpers"), f"{rel} imports {module}"


def test_bench_scripts_leave_sys_path_alone():
    for path in BENCH.glob("*.py"):
        assert "sys.path." not in path.read_text(encoding="utf-8"), path.name


@pytest.mark.slow
def test_each_bench_script_runs_as_a_module():
    """``python -m bench.NAME --help`` from the root, all at once: imports resolve, options
    parse."""
    procs = {name: subprocess.Popen([sys.executable, "-m", f"bench.{name}", "--help"], cwd=ROOT,
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for name in SCRIPTS}  # fmt: skip
    for name, proc in procs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0 and out.startswith("usage:"), f"bench.{name}: {err}"
