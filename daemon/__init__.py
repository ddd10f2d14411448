"""loopcal's daemon and commands: the data flow DAQ -> scans -> MCAP -> poses -> fit -> gates
-> config, one sub-package per job (docs/architecture.md draws the map):

- :mod:`loopcal.daemon.scan_rows`, :mod:`loopcal.daemon.events`, :mod:`loopcal.daemon.version`: the
  base
  every job shares (a scan row, an event, the version);
- :mod:`loopcal.daemon.config`: the controller config and durable writes;
- :mod:`loopcal.daemon.recording`: the recording format (schemas, CDR, views, writer, reader);
- :mod:`loopcal.daemon.recorder`: DAQ -> scans -> MCAP, the acquisition engine and service;
- :mod:`loopcal.daemon.worker`: MCAP -> poses -> fit -> gates -> config, the calibration worker;
- :mod:`loopcal.daemon.live`: live analysis plugged into the recorder (health, guidance);
- :mod:`loopcal.daemon.commands`: the ``loopcal`` commands, loaded lazily;
- :mod:`loopcal.daemon.cli`: parses the command line and dispatches.

Imports run one way, down this list read bottom up (import-linter checks it: the
``[tool.importlinter]`` contracts in pyproject.toml).
"""
