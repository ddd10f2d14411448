"""``loopcal simulate``: the emulated LDQ-412 driven by a simulated shoulder joint (the
command itself lives with the simulator, in :mod:`loopcal.simulator.run`)."""

from loopcal.simulator.run import __doc__ as DESCRIPTION  # noqa: N812
from loopcal.simulator.run import add_arguments, run

__all__ = ["DESCRIPTION", "add_arguments", "run"]
