"""Start-up time of the ``loopcal`` command, against importing numpy and scipy.linalg.

    python -m bench.bench_startup [--repeats 15]

Every command is a fresh process (``python -m loopcal.daemon.cli ...``), timed wall to wall, the
runs of all commands interleaved so that a busy machine slows them alike; medians:

* baseline: ``python -c "import numpy, scipy.linalg"`` (what any numerical command pays);
* ``loopcal --help`` (target: at most 1.3x the baseline: it imports no command);
* ``loopcal calibrate`` of a two-minute recording (target: at most 2x: the fit on every
  scan, twice, takes about 0.25 s; the rest is imports, reading and the gates);
* ``loopcal calibrate --help`` and ``loopcal record --help`` for reference.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

from bench._timing import interleaved_medians
from loopcal.daemon.config.controller import write_initial_config
from loopcal.simulator.scenarios import HandMoves
from tests.support.sessions import PAUSE_S, truth_for, write_session

PY = sys.executable


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=15)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        truth = truth_for(4)
        write_session(work / "rec", HandMoves(4, params=truth, pause_s=PAUSE_S), truth, 120,
                      seed=4)  # fmt: skip
        config = write_initial_config(work / "controller.toml")
        cli = [PY, "-m", "loopcal.daemon.cli"]
        cases = {
            "baseline: import numpy, scipy.linalg": [PY, "-c", "import numpy, scipy.linalg"],
            "loopcal --help": [*cli, "--help"],
            "loopcal calibrate (2-minute recording)": [
                *cli, "calibrate", str(work / "rec"), "--controller-config", str(config)],
            "loopcal calibrate --help": [*cli, "calibrate", "--help"],
            "loopcal record --help": [*cli, "record", "--help"],
        }  # fmt: skip
        medians = interleaved_medians(cases, args.repeats, ok=(0, 1))  # 1: a gate refused
    base = medians["baseline: import numpy, scipy.linalg"]
    print(f"medians of {args.repeats} fresh processes each, interleaved:")
    for name, med in medians.items():
        print(f"  {name:<40} {med:6.3f} s  {med / base:5.2f}x the baseline")
    help_ratio = medians["loopcal --help"] / base
    cal_ratio = medians["loopcal calibrate (2-minute recording)"] / base
    print(f"loopcal --help: {help_ratio:.2f}x the baseline (target <= 1.3x: "
          f"{'met' if help_ratio <= 1.3 else 'NOT met'})")  # fmt: skip
    print(f"loopcal calibrate of a two-minute recording: {cal_ratio:.2f}x the baseline (target "
          f"<= 2x: {'met' if cal_ratio <= 2 else 'NOT met'})")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
