"""Inspecting archived recordings: what they hold (:mod:`~loopcal.daemon.inspect.summary`), whether
the loops closed (:mod:`~loopcal.daemon.inspect.loops`), and both over a fleet of robots on Dask
(:mod:`~loopcal.daemon.inspect.fleet`).

Imports: live analysis (the health monitor), the worker's poses, the recording format, the
config and the base modules. Only the commands import it.
"""
