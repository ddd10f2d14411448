"""The recorder: DAQ -> scans -> MCAP, the acquisition engine and the service around it.

- :mod:`~daemon.recorder.acquisition`: the thread that reads the module through a driver
  and turns its scans into rows with epochs, UTC stamps and events, handed on as
  :mod:`~daemon.recorder.batches`; without a FIFO it polls phase-locked to the module's clock
  (:mod:`~daemon.recorder.polling`), and it stamps device time as UTC through a map that
  follows the module's clock error (:mod:`~daemon.recorder.clockmap`);
- :mod:`~daemon.recorder.engine`: the :class:`~daemon.recorder.engine.Recorder` (three
  threads: acquisition, writer, the caller's) writing rotating recording files;
- :mod:`~daemon.recorder.observers`: the analysis thread that feeds every scan to observers
  (live analysis plugs in here);
- :mod:`~daemon.recorder.settings`: the recorder's settings and the daemon's TOML config;
- :mod:`~daemon.recorder.filewriter`, :mod:`~daemon.recorder.resume`: the writer thread
  (flushes, rotation, retention, a full disk) and where a new recorder carries on;
- :mod:`~daemon.recorder.compactor`: closed files rewritten with large chunks after rotation;
- :mod:`~daemon.recorder.metrics`: the Prometheus endpoint;
- :mod:`~daemon.recorder.sdnotify`, :mod:`~daemon.recorder.process`: systemd notification,
  logging and signals for the long-running commands.

Imports: drivers/, the recording format (:mod:`daemon.recording`), the shared config
(:mod:`daemon.config`) and the base modules (:mod:`daemon.scans`, :mod:`daemon.events`).
Never the worker, live analysis or the commands.
"""
