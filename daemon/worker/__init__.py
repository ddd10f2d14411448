"""The calibration worker: MCAP -> poses -> fit -> gates -> config.

- :mod:`~daemon.worker.poses`: still poses from recorded scans;
- :mod:`~daemon.worker.gates`: the acceptance gates a result must pass;
- :mod:`~daemon.worker.run`: :func:`~daemon.worker.run.run_worker`, from scans to a
  :class:`~daemon.worker.run.WorkerResult` it can vouch for;
- :mod:`~daemon.worker.writeback`: the accepted values into the controller config, safely;
- :mod:`~daemon.worker.report`: the HTML report with plots (matplotlib, loaded only for it).

Imports: calibration/, the recording format (:mod:`daemon.recording`), the shared config
(:mod:`daemon.config`) and the base modules. Never the recorder, live analysis or the
commands.
"""
