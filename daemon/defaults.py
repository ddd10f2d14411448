"""The daemon's defaults that a command's ``--help`` prints, in a module that imports nothing:
``loopcal check --help`` (and ``fleet check``) reads them without waiting for numpy, and the
daemon's settings (:class:`loopcal.daemon.recorder.settings.RecorderSettings`) take them from
here, so that each is written once.
"""

from __future__ import annotations

#: probability per still pose of a loop-closure alarm when nothing moved, the daemon's
#: ``[health].false_alarm``
FALSE_ALARM = 1e-8
#: the health monitor's false-alarm rate must be below this
FALSE_ALARM_MAX = 1e-2
#: mm, the standard deviation an offset the upkeep proposes must reach (``[upkeep].target_mm``)
UPKEEP_TARGET_MM = 0.05
#: mm, the smallest change of an offset the upkeep acts on (``[upkeep].threshold_mm``)
UPKEEP_THRESHOLD_MM = 0.1
#: s of the scans' stamps, what the upkeep screens at a time (``[upkeep].segment``)
UPKEEP_SEGMENT_S = 10.0
