"""What loopcal ships beside its code: the systemd units, the sysusers and tmpfiles entries,
the Foxglove layouts and the documentation, as package data (``loopcal files`` lists them,
``loopcal install-units`` puts the units in place).

In the repository they are ``systemd/`` and ``docs/``; installed, the packages
``loopcal.systemd`` and ``loopcal.docs`` (pyproject.toml maps them), so that a wheel's user
finds the same files as a checkout's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: where loopcal.systemd and loopcal.docs are: beside loopcal.daemon, installed (site-packages/
#: loopcal/docs) as in a checkout (docs/ beside daemon/). importlib.resources cannot be asked:
#: data-only namespace packages have no directory of their own under an editable install.
ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Shipped:
    """One shipped file.

    name: how ``loopcal files NAME`` names it (``systemd/...`` or ``docs/...``, its path in
    the repository); installs_to: where ``loopcal install-units`` puts it, relative to the
    root (None: it is not installed); what: one line on what it is."""

    name: str
    installs_to: str | None
    what: str

    @property
    def path(self) -> Path:
        """The file itself, where loopcal is installed (in a checkout: the repository's)."""
        return ROOT / self.name


UNITS: tuple[Shipped, ...] = (
    Shipped("systemd/loopcal.service", "etc/systemd/system/loopcal.service",
            "the acquisition daemon (Type=notify, watchdog, reload), as user loopcal"),
    Shipped("systemd/loopcal-calibrate.service", "etc/systemd/system/loopcal-calibrate.service",
            "the one-shot calibration worker (the last 15 minutes of recordings)"),
    Shipped("systemd/sysusers.d/loopcal.conf", "etc/sysusers.d/loopcal.conf",
            "the system user loopcal, a member of dialout (systemd-sysusers)"),
    Shipped("systemd/tmpfiles.d/loopcal.conf", "etc/tmpfiles.d/loopcal.conf",
            "/var/lib/loopcal/recordings, /etc/loopcal and its controller/ (systemd-tmpfiles)"),
)  # fmt: skip


def shipped() -> list[Shipped]:
    """Every shipped file: the units and their companions, then systemd/README.md, the
    Foxglove layouts and the docs, each group sorted by name."""
    files = [*UNITS, Shipped("systemd/README.md", None, "installing and watching the service")]
    docs = ROOT / "docs"
    layouts = sorted(p.name for p in (docs / "foxglove").glob("*.json"))
    files += [Shipped(f"docs/foxglove/{name}", None,
                      "a Foxglove layout (Layouts > Import from file)") for name in layouts]
    pages = sorted(p.name for p in docs.glob("*.md"))
    files += [Shipped(f"docs/{name}", None, _title((docs / name).read_text()))
              for name in pages]  # fmt: skip
    return files


def _title(markdown: str) -> str:
    """A page's first heading (or first line), without its #."""
    return next((line.lstrip("#").strip() for line in markdown.splitlines() if line.strip()), "")
