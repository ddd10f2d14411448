"""Sphinx configuration of the API reference (docs/api.md says how to build it).

The reference is built from the docstrings of the installed package (``pip install -e .``
first), numpy style, with warnings as errors in the tests (tests/project/test_api_docs.py). This is
the only Python file under docs/; it is not package data (pyproject.toml ships docs/*.md).
"""

import re

project = "loopcal"
author = "loopcal developers"
copyright = "loopcal developers, MIT licence"

extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon"]

root_doc = "index"
exclude_patterns = ["_build"]
html_theme = "alabaster"  # ships with Sphinx: nothing to download
html_static_path: list[str] = []

# numpy-style sections (Parameters, Returns, Raises, Attributes, Notes), nothing else
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_include_init_with_doc = False
napoleon_use_rtype = False

autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_typehints_format = "short"
# defaults as written in the source (NOMINAL, PAPER7), not the repr of an array
autodoc_preserve_defaults = True
autoclass_content = "class"


# The packages whose docstrings are numpy style. tests/project/test_api_docs.py checks that every
# public function and class of each is in the reference with a Parameters, Returns or
# Attributes section. Add a package here (one line) once its docstrings are written.
NUMPY_STYLE = ("loopcal.calibration", "loopcal.drivers", "loopcal.simulator",
               "loopcal.daemon.recording.reader", "loopcal.daemon.worker.gates",
               "loopcal.daemon.worker.coverage")

# In the modules not listed yet (the rest of daemon/), a docstring with no numpy section
# is shown as written, in a literal block, instead of being parsed as reStructuredText:
# the older, free-form ones would otherwise
# fail the build under -W. A docstring with a section is parsed like any other, and its
# warnings are errors, as are all of a listed package's.
_SECTION = re.compile(
    r"^(Parameters|Other Parameters|Returns|Yields|Receives|Raises|Warns|Attributes|Methods"
    r"|Notes|Examples|See Also|References|Warnings)\n-{3,}$",
    re.M,
)


def _listed(name: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in NUMPY_STYLE)


def _verbatim_if_not_numpy_style(app, what, name, obj, options, lines):
    if _listed(name) or not lines:
        return
    if _SECTION.search("\n".join(line.rstrip() for line in lines)):
        return
    lines[:] = ["::", ""] + [f"    {line}" if line.strip() else "" for line in lines] + [""]


def setup(app):
    # before napoleon's own handler (priority 500), which would see the literal block
    app.connect("autodoc-process-docstring", _verbatim_if_not_numpy_style, priority=100)
