"""The recorder: DAQ -> scans -> MCAP, the acquisition engine and the service around it.

- :mod:`~loopcal.daemon.recorder.acquisition`: the thread that reads the module through a driver
  and turns its scans into rows with epochs, UTC stamps and events, handed on as
  :mod:`~loopcal.daemon.recorder.batches`; it reads at the pace of the driver's own pacers
  (:mod:`loopcal.drivers.pacing`: without a FIFO, polls phase-locked to the module's clock),
  and it stamps device time as UTC through a map
  that follows the module's clock error (:mod:`~loopcal.daemon.recorder.clockmap`); another
  Modbus master taking scans off the module's FIFO is told as one episode
  (:mod:`~loopcal.daemon.recorder.foreign`);
- :mod:`~loopcal.daemon.recorder.ownership`: one owner of a module on the host (the module's
  lock, taken before it is opened);
- :mod:`~loopcal.daemon.recorder.engine`: the :class:`~loopcal.daemon.recorder.engine.Recorder`
  (three threads: acquisition, writer, the caller's) writing rotating recording files;
- :mod:`~loopcal.daemon.recorder.observers`: the analysis thread that feeds every scan to observers
  (live analysis plugs in here);
- :mod:`~loopcal.daemon.recorder.settings`: the recorder's settings and the daemon's TOML config;
- :mod:`~loopcal.daemon.recorder.filewriter`, :mod:`~loopcal.daemon.recorder.resume`: the writer
  thread (flushes, rotation, retention, a full disk) and where a new recorder carries on;
- :mod:`~loopcal.daemon.recorder.compactor`: closed files rewritten in chunks of a minute after
  rotation;
- :mod:`~loopcal.daemon.recorder.metrics`: the Prometheus endpoint;
- :mod:`~loopcal.daemon.recorder.sdnotify`, :mod:`~loopcal.daemon.recorder.process`: systemd
  notification, logging and signals for the long-running commands.

Imports: drivers/, the recording format (:mod:`loopcal.daemon.recording`), the shared config
(:mod:`loopcal.daemon.config`) and the base modules (:mod:`loopcal.daemon.scan_rows`,
:mod:`loopcal.daemon.events`). Never the worker, live analysis or the commands.
"""
