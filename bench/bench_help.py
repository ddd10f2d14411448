"""How long ``loopcal X --help`` takes for every command, against importing numpy and scipy.

    python -m bench.bench_help [--repeats 15] [--commands record daemon ...]

Every run is a fresh process (``python -m loopcal.daemon.cli X --help``), timed wall to wall,
the runs of all commands interleaved with the baseline's so that a busy machine slows them
alike; medians. The baseline is ``python -c "import numpy, scipy.linalg"`` in the same run
(what any numerical command pays); the target is at most half of it for every command, which
holds when building a command's parser imports none of the analysis (issue 32; the commands
import their machinery in ``run``, docs/architecture.md).
"""

from __future__ import annotations

import sys

from bench._timing import interleaved_medians, repeats_parser
from loopcal.daemon.commands import COMMANDS

PY = sys.executable
BASELINE = "baseline: import numpy, scipy.linalg"
#: every command's --help takes at most this fraction of the baseline
TARGET = 0.5


def main() -> int:
    ap = repeats_parser(__doc__, default=15)
    names = [name for name, _ in COMMANDS]
    ap.add_argument("--commands", nargs="+", choices=names, default=names, metavar="NAME",
                    help="the commands to time (default: every one)")  # fmt: skip
    args = ap.parse_args()
    cli = [PY, "-m", "loopcal.daemon.cli"]
    cases = {BASELINE: [PY, "-c", "import numpy, scipy.linalg"], "loopcal --help": [*cli, "--help"]}
    cases |= {f"loopcal {name} --help": [*cli, name, "--help"] for name in args.commands}
    medians = interleaved_medians(cases, args.repeats)
    base = medians[BASELINE]
    print(f"medians of {args.repeats} fresh processes each, interleaved:")
    for name, med in medians.items():
        print(f"  {name:<42} {med:6.3f} s  {med / base:5.2f}x the baseline")
    missed = [name for name, med in medians.items() if name != BASELINE and med > TARGET * base]
    print(f"target: every --help at most {TARGET:g}x the baseline: "
          + (f"NOT met by {', '.join(missed)}" if missed else "met"))  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
