"""Inspecting archived recordings: what they hold (:mod:`~daemon.inspect.summary`), whether
the loops closed (:mod:`~daemon.inspect.loops`), and both over a fleet of robots on Dask
(:mod:`~daemon.inspect.fleet`).

Imports: live analysis (the health monitor), the worker's poses, the recording format, the
config and the base modules. Only the commands import it.
"""
