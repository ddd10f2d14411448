"""``loopcal files [NAME ...] [--json]``: the files loopcal ships beside its code, where this
installation keeps them: the systemd units and their sysusers and tmpfiles entries, the
Foxglove layouts and the documentation (the repository's systemd/ and docs/ folders,
installed with the package, so a wheel's user has them too).

With no NAME, one line each: the file's path and what it is. With NAMEs (as listed, e.g.
docs/daemon.md or systemd/loopcal.service), their paths alone, one a line, for a shell:

    install -m 0644 "$(loopcal files systemd/loopcal.service)" /etc/systemd/system/

Exit status 0, or 2 for a name loopcal does not ship (the names it does on stderr)."""

from __future__ import annotations

import argparse
import json

from ..shipped import shipped
from .errors import CommandError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("names", nargs="*", metavar="NAME",
                   help="print only these files' paths (as listed, e.g. docs/daemon.md)")
    p.add_argument("--json", action="store_true",
                   help="one JSON object: files, a list of {name, path, installs_to, what}")


def run(args: argparse.Namespace) -> int:
    files = shipped()
    by_name = {f.name: f for f in files}
    unknown = [n for n in args.names if n not in by_name]
    if unknown:
        raise CommandError(f"not shipped: {', '.join(unknown)} "
                           f"(shipped: {', '.join(by_name)})")  # fmt: skip
    chosen = [by_name[n] for n in args.names] if args.names else files
    if args.json:
        print(json.dumps({"files": [
            {"name": f.name, "path": str(f.path), "installs_to": f.installs_to, "what": f.what}
            for f in chosen]}, indent=2))  # fmt: skip
    elif args.names:
        print("\n".join(str(f.path) for f in chosen))
    else:
        width = max(len(f.name) for f in chosen)
        for f in chosen:
            print(f"{f.name:<{width}}  {f.what}\n{'':<{width}}  {f.path}")
    return 0
