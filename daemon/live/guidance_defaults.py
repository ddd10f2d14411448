"""The live guidance's defaults that a command's ``--help`` prints (``loopcal record
--until-enough``, ``loopcal session``), in a module that imports nothing: the help does not
wait for numpy and the worker, and the guidance (:mod:`loopcal.daemon.live.guidance`) takes
them from here, so that each is written once.
"""

from __future__ import annotations

#: the default target: every offset's predicted standard deviation, mm
TARGET_MM = 0.1
#: the largest target a session or a recording may ask for, mm: beyond it the guidance
#: would call any motion enough
MAX_TARGET_MM = 10.0
