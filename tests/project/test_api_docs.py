"""The API reference (docs/api/, Sphinx with autodoc and napoleon): it builds with warnings as
errors, as CI builds it, and every public function and class of the packages whose docstrings
are numpy style is in it, with a Parameters, Returns or Attributes section.

Those packages are docs/api/conf.py's ``NUMPY_STYLE`` (calibration/, drivers/, simulator/,
the recording reader and the gates):
adding one there is one line, and both the build's strictness and these checks follow. Public:
a name without a leading underscore, defined in that module (not imported into it), listed in
the module's ``__all__`` where it has one.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
import runpy
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest

from tests.support import ROOT

SOURCE = ROOT / "docs" / "api"
NUMPY_STYLE: tuple[str, ...] = runpy.run_path(str(SOURCE / "conf.py"))["NUMPY_STYLE"]

# a numpy-style section header: the name, then a line of dashes
SECTION = re.compile(r"^(Parameters|Returns|Attributes)\n-{3,}$", re.M)

pytestmark = pytest.mark.timeout(900)  # a full build: about 20 s of CPU, more on a busy CI


@pytest.fixture(scope="module")
def build(tmp_path_factory: pytest.TempPathFactory) -> tuple[subprocess.CompletedProcess, Path]:
    """The reference built from scratch, exactly as docs/api.md says, into a temporary dir."""
    out = tmp_path_factory.mktemp("api")
    proc = subprocess.run(
        [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", str(SOURCE),
         str(out)],
        capture_output=True, text=True, timeout=840, cwd=ROOT,
    )  # fmt: skip
    return proc, out


@pytest.fixture(scope="module")
def documented(build: tuple[subprocess.CompletedProcess, Path]) -> set[int]:
    """The objects the built HTML documents (by identity: a name re-exported by its package,
    such as ``loopcal.daemon.recording.Recording``, is the object of its defining module)."""
    _, out = build
    ids = set()
    for page in out.glob("*.html"):
        ids |= set(re.findall(r'id="(loopcal\.[\w.]+)"', page.read_text(encoding="utf-8")))
    assert ids, "the build wrote no documented objects"
    return {id(obj) for obj in map(_resolve, ids) if obj is not None}


def _resolve(dotted: str) -> object | None:
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for attr in parts[cut:]:
                obj = getattr(obj, attr)
        except AttributeError:
            return None
        return obj
    return None


def _modules(package: str) -> Iterator[ModuleType]:
    top = importlib.import_module(package)
    yield top
    for info in pkgutil.walk_packages(getattr(top, "__path__", []), package + "."):
        yield importlib.import_module(info.name)


def public_objects(package: str) -> list[tuple[str, object]]:
    """(dotted name, object) of every public function and class of the package's modules."""
    found = []
    for module in _modules(package):
        names = getattr(module, "__all__", None)
        if names is None:
            names = [n for n in vars(module) if not n.startswith("_")]
        for name in names:
            obj = getattr(module, name, None)
            if name.startswith("_") or not (inspect.isfunction(obj) or inspect.isclass(obj)):
                continue
            if obj.__module__ == module.__name__:
                found.append((f"{module.__name__}.{name}", obj))
    return found


@pytest.mark.slow
def test_the_reference_builds_with_warnings_as_errors(
    build: tuple[subprocess.CompletedProcess, Path],
) -> None:
    proc, out = build
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-8000:]
    for page in ("index", "calibration", "drivers", "simulator", "recording", "gates"):
        assert (out / f"{page}.html").is_file(), page


@pytest.mark.slow
@pytest.mark.parametrize("package", NUMPY_STYLE)
def test_every_public_object_is_in_the_reference(package: str, documented: set[int]) -> None:
    objects = public_objects(package)
    assert objects, f"{package} has no public functions or classes?"
    missing = [name for name, obj in objects if id(obj) not in documented]
    assert not missing, f"not in the API reference (no docstring, or no page): {missing}"


def _takes_arguments(obj: object) -> bool:
    """Whether a numpy section has anything to say: not for a function a factory made (its
    factory's docstring does), an exception, a Protocol, or a class built with no
    arguments (its summary and its methods' sections say it all)."""
    if inspect.isfunction(obj):
        return "<locals>" not in obj.__qualname__
    if issubclass(obj, BaseException) or getattr(obj, "_is_protocol", False):
        return False
    try:
        return bool(inspect.signature(obj).parameters)
    except (TypeError, ValueError):
        return True


@pytest.mark.parametrize("package", NUMPY_STYLE)
def test_every_public_object_has_a_numpy_style_docstring(package: str) -> None:
    # the object's own docstring: a class without one does not inherit its base's here
    bare = [name for name, obj in public_objects(package)
            if _takes_arguments(obj)
            and not SECTION.search(inspect.cleandoc(obj.__doc__ or ""))]  # fmt: skip
    assert not bare, f"no Parameters, Returns or Attributes section: {bare}"
