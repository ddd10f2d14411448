"""The fuzz tests' Hypothesis profiles (tests/support/fuzz.py): a test's examples are its
share at ``ci``, and ``--hypothesis-profile`` scales every one of them."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.support import ROOT
from tests.support.fuzz import SCALES, examples

FUZZED = "tests/daemon/recorder/test_clockmap.py::test_stamps_never_go_back_whatever_the_answers"


def test_each_profile_scales_a_tests_examples():
    assert [examples(300, p) for p in ("ci", "dev", "deep")] == [300, 30, 6000]
    assert examples(3, "dev") == 1  # never none
    assert set(SCALES) == {"ci", "dev", "deep"}


def test_every_fuzz_test_gives_its_examples_through_the_profiles():
    fixed = [f"{path.relative_to(ROOT)}:{i}" for path in (ROOT / "tests").rglob("*.py")
             for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
             if re.search(r"max_examples\s*=\s*\d", line)]  # fmt: skip
    assert not fixed, f"max_examples=examples(N) (tests/support/fuzz.py), not N: {fixed}"


@pytest.mark.slow
@pytest.mark.parametrize(("profile", "n"), [("ci", 300), ("dev", 30)])
def test_the_command_line_chooses_the_profile(profile, n):
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-n", "0", "-p", "no:cacheprovider", FUZZED,
         f"--hypothesis-profile={profile}", "--hypothesis-show-statistics"],
        capture_output=True, text=True, cwd=ROOT, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stdout[-2000:]
    assert f"Stopped because settings.max_examples={n}" in proc.stdout, proc.stdout[-2000:]
