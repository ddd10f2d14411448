"""``loopcal install-units ROOT [--force] [--dry-run]``: put the systemd units and their
sysusers and tmpfiles entries in place under ROOT (``/`` on the robot's controller; a
staging folder for an image):

    ROOT/etc/systemd/system/loopcal.service, loopcal-calibrate.service
    ROOT/etc/sysusers.d/loopcal.conf
    ROOT/etc/tmpfiles.d/loopcal.conf

Each is written atomically (mode 0644); one already there with the same bytes is left as
it is; one that differs (edited by hand) is not replaced without ``--force``. Then, on the
controller: ``systemd-sysusers && systemd-tmpfiles --create && systemctl daemon-reload``
(systemd/README.md, ``loopcal files systemd/README.md``). The units run
``/opt/loopcal/bin/loopcal``: install loopcal into a venv there, or change ExecStart by a
drop-in.

Exit status 0 when every file is in place, 1 when a differing file was kept (nothing of it
changed; named on stderr), 2 for a ROOT that is not a directory or a file that cannot be
written."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from ..arguments import path_argument
from ..config.durable import replace
from ..shipped import UNITS
from .errors import CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("root", type=path_argument, metavar="ROOT",
                   help="the root to install under: / on the controller, or a staging folder")
    p.add_argument("--force", action="store_true",
                   help="replace files that differ from loopcal's (edited by hand)")
    p.add_argument("--dry-run", action="store_true",
                   help="say what would be written, write nothing")


def run(args: argparse.Namespace) -> int:
    root: Path = args.root
    if not root.is_dir():
        raise CommandError(f"{str(root)!r} is not a directory")
    kept = []
    for unit in UNITS:
        assert unit.installs_to is not None
        target = root / unit.installs_to
        data = unit.path.read_bytes()
        try:
            current = target.read_bytes() if target.exists() else None
        except OSError as exc:
            raise CommandError(f"cannot read {target}: {exc.strerror or exc}") from None
        if current == data:
            print(f"unchanged {target}")
            continue
        if current is not None and not args.force:
            kept.append(target)
            continue
        verb = "would write" if args.dry_run else ("replaced" if current is not None else "wrote")
        if not args.dry_run:
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                replace(target, data, mode=0o644)
            except OSError as exc:
                raise CommandError(f"cannot write {target}: {exc.strerror or exc}") from None
        print(f"{verb} {target}")
    if kept:  # exit status 1: the others are in place
        raise CommandError("\n".join(f"{target} differs from loopcal's and was kept (--force "
                           "replaces it)" for target in kept), status=1)  # fmt: skip
    if not args.dry_run and os.geteuid() == 0 and root.resolve() == Path("/"):
        print("next: systemd-sysusers && systemd-tmpfiles --create && systemctl daemon-reload")
    return 0
