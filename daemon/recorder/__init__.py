"""The recorder: DAQ -> scans -> MCAP, the acquisition engine and the service around it.

- :mod:`~daemon.recorder.acquisition`: the thread that reads the module through a driver
  and turns its scans into rows with epochs, UTC stamps and events;
- :mod:`~daemon.recorder.engine`: the :class:`~daemon.recorder.engine.Recorder` (three
  threads: acquisition, writer, the caller's) writing rotating recording files;
- :mod:`~daemon.recorder.observers`: the analysis thread that feeds every scan to observers
  (live analysis plugs in here);
- :mod:`~daemon.recorder.settings`: the recorder's settings and the daemon's TOML config;
- :mod:`~daemon.recorder.sdnotify`, :mod:`~daemon.recorder.process`: systemd notification,
  logging and signals for the long-running commands.

Imports: drivers/, the recording format (:mod:`daemon.recording`), the shared config
(:mod:`daemon.config`) and the base modules (:mod:`daemon.scans`, :mod:`daemon.events`).
Never the worker, live analysis or the commands.
"""
