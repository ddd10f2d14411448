"""Live analysis: observers the recorder feeds every scan to while it records.

- :mod:`~loopcal.daemon.live.health`: loop-closure health, which names the sensor whose offset
  moved (``offset_drift`` events);
- :mod:`~loopcal.daemon.live.guidance`: the technician's live guidance (``record --until-enough``);
- :mod:`~loopcal.daemon.live.view`: the session served live to Foxglove over its WebSocket
  protocol (``record --live``, ``[live].listen``), with foxglove-sdk.

Imports: the worker (its poses, gates and fit are what live analysis runs), the recorder's
observer protocol, settings and metrics, the recording format's views and schemas (the live
view serves the recording's channels), the shared config and the base modules. Only the
commands import it.
"""
