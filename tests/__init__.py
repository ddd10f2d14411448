"""loopcal's tests, in one folder per package of the code (calibration/, drivers/,
simulator/, daemon/ with a folder per sub-package, systemd/) and project/ for what spans
them (packaging, API docs, layouts, alert rules). What they share is in
:mod:`tests.support`; their fixtures in conftest.py."""
