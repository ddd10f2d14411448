"""How the suite's tests are shared among pytest-xdist's workers (``pytest_xdist_make_scheduler``
in tests/conftest.py; docs/architecture.md, "Workers").

Each test goes to whichever worker is free, one at a time, except the tests of a file that
makes a fixture once for the whole file (``scope="module"``: a recorded technician session,
a Sphinx build, a wheel): those go together to one worker, which makes the fixture once.

xdist's own ``--dist loadgroup`` would say the same with marks, but it is broken on pytest
9.2 (the group suffix it writes into the node id is lost: pytest-xdist issue 1386), and
``--dist loadfile`` keeps a file's long real-time tests on one worker while others idle.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

from xdist.scheduler import LoadScopeScheduling

#: a fixture made once per file: ``@pytest.fixture(scope="module")``
MODULE_FIXTURE = re.compile(r"""@pytest\.fixture\([^)]*scope\s*=\s*["']module["']""")


@cache
def makes_module_fixture(path: Path) -> bool:
    """Whether the test file at ``path`` defines a fixture made once for the file.

    Parameters
    ----------
    path : Path
        A test file.

    Returns
    -------
    bool
        True when its text holds ``@pytest.fixture(..., scope="module")``.
    """
    try:
        return MODULE_FIXTURE.search(path.read_text(encoding="utf-8")) is not None
    except OSError:  # not a file (a doctest's module, say): a test alone
        return False


class SharedFixtureScheduling(LoadScopeScheduling):
    """xdist's scope scheduling, the scope a single test, or the file for a file that
    makes a module fixture (module docstring).

    Parameters
    ----------
    config : pytest.Config
        The controller's configuration; its root path resolves the node ids' files.
    log : xdist.remote.Producer or None
        xdist's trace log.
    """

    def __init__(self, config, log=None) -> None:
        super().__init__(config, log)
        self.root = Path(config.rootpath)

    def _split_scope(self, nodeid: str) -> str:
        path = nodeid.split("::", 1)[0]
        return path if makes_module_fixture(self.root / path) else nodeid
