"""A figure the docs and the help texts state in several places is the same everywhere, and
the one the code or the measurement behind it gives: a reader who meets two numbers for
one thing cannot tell which is true."""

from __future__ import annotations

import re

from loopcal.daemon.cli import build_parser
from loopcal.daemon.commands import COMMANDS
from loopcal.daemon.recorder.engine import FOLLOW_CONFIG_S
from tests.support import ROOT


def _texts() -> dict[str, str]:
    """Every page a user reads: the README, docs/*.md, systemd/README.md and each
    command's --help; whitespace folded, so that a claim may break across lines."""
    docs = sorted((ROOT / "docs").glob("*.md"))
    pages = [ROOT / "README.md", ROOT / "systemd" / "README.md", *docs]
    out = {str(p.relative_to(ROOT)): p.read_text(encoding="utf-8") for p in pages}
    for name, _ in COMMANDS:
        parser = build_parser(name)
        sub = next(a for a in parser._actions if a.dest == "command")
        out[f"loopcal {name} --help"] = sub.choices[name].format_help()
    return {k: " ".join(v.split()) for k, v in out.items()}


def _claims(pattern: str) -> dict[str, set[str]]:
    found: dict[str, set[str]] = {}
    for where, text in _texts().items():
        for m in re.finditer(pattern, text):
            found.setdefault(m.group(1), set()).add(where)
    return found


def _measured_bytes_a_scan() -> float:
    """docs/recording.md's measured table: a compacted day without views, bytes a scan."""
    text = (ROOT / "docs" / "recording.md").read_text(encoding="utf-8")
    m = re.search(r"^\| bytes a scan, in all \| ([\d.]+) \| ([\d.]+) \|$", text, re.M)
    assert m, "docs/recording.md's measured table is gone"
    return float(m.group(2))


def test_one_figure_for_the_bytes_a_scan_without_views() -> None:
    claims = _claims(r"about (\d+(?:\.\d+)?) bytes a scan")
    assert len(claims) == 1, claims
    (said,) = claims
    assert round(_measured_bytes_a_scan()) == float(said), (said, _measured_bytes_a_scan())


def test_one_figure_for_how_soon_the_daemon_follows_a_new_config() -> None:
    claims = _claims(r"(?:follows|notices)[^.]*? within about (\d+(?:\.\d+)?) s\b")
    assert claims, "no page says how soon the daemon follows a new config"
    assert set(claims) == {f"{FOLLOW_CONFIG_S:g}"}, claims


def test_no_page_says_a_reload_is_needed_for_a_written_config() -> None:
    """The daemon follows a written controller config by itself; a reload is not needed."""
    for where, text in _texts().items():
        assert not re.search(r"(next|a) `?systemctl reload`? (picks|to pick) up", text), where
