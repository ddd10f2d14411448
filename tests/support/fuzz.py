"""Hypothesis profiles for the fuzz tests. Each test gives its examples as its share at the
``ci`` profile (``max_examples=examples(300)``: what it can afford in CI), and the profile
in force scales them all:

- ``ci``, the default (``.ci/run``, the fast loop): the counts the tests give;
- ``dev``, a tenth of them (at least one): ``pytest --hypothesis-profile=dev`` while
  working on a parser;
- ``deep``, twenty times as many: a night's fuzzing,
  ``pytest --hypothesis-profile=deep tests/daemon/test_parsers_fuzz.py``.

Every profile turns Hypothesis's deadline off (a busy machine stalls any one example) and
prints the blob that reproduces a failure. ``tests/conftest.py`` registers them and loads
``ci``; Hypothesis's pytest plugin loads the one ``--hypothesis-profile`` names.
"""

from __future__ import annotations

from hypothesis import settings

#: profile -> its examples as a multiple of ``ci``'s
SCALES = {"ci": 1.0, "dev": 0.1, "deep": 20.0}
_CI_EXAMPLES = 100  # ci's own max_examples, Hypothesis's default: the unit of the scale


def register() -> None:
    """Register the profiles (:data:`SCALES`) with Hypothesis and load ``ci``."""
    for name, scale in SCALES.items():
        settings.register_profile(
            name, max_examples=round(_CI_EXAMPLES * scale), deadline=None, print_blob=True
        )
    settings.load_profile("ci")


def examples(n: int, profile: str | None = None) -> int:
    """A test's examples: ``n`` at the ``ci`` profile, scaled to ``profile`` (None: the
    profile in force), at least one."""
    chosen = settings.default if profile is None else settings.get_profile(profile)
    return max(1, round(n * chosen.max_examples / _CI_EXAMPLES))
