"""The calibration worker: MCAP -> poses -> fit -> gates -> config.

- :mod:`~loopcal.daemon.worker.scan_poses`: the poses of a fit on every scan: each usable
  scan, moving or still, its channel skew corrected (maximum likelihood, the default);
- :mod:`~loopcal.daemon.worker.recorded_poses`: still poses from recorded scans (the paper's
  method, and the live health);
- :mod:`~loopcal.daemon.worker.gates`: the acceptance gates a result must pass;
- :mod:`~loopcal.daemon.worker.job`: :func:`~loopcal.daemon.worker.job.run_worker`, from
  scans to a :class:`~loopcal.daemon.worker.job.WorkerResult` it can vouch for;
- :mod:`~loopcal.daemon.worker.writeback`: the accepted values into the controller config, safely;
- :mod:`~loopcal.daemon.worker.report`: the HTML report with plots (matplotlib, loaded only for it).

Imports: calibration/, the recording format (:mod:`loopcal.daemon.recording`), the shared config
(:mod:`loopcal.daemon.config`) and the base modules. Never the recorder, live analysis or the
commands.
"""
