"""Live analysis: observers the recorder feeds every scan to while it records.

- :mod:`~loopcal.daemon.live.health`: loop-closure health, which names the sensor whose offset
  moved (``offset_drift`` events);
- :mod:`~loopcal.daemon.live.guidance`: the technician's live guidance (``record --until-enough``).

Imports: the worker (its poses, gates and fit are what live analysis runs), the recorder's
observer protocol, the shared config and the base modules. Only the commands import it.
"""
