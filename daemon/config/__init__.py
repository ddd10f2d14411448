"""Files people configure, and how they are written: the controller config
(:mod:`~loopcal.daemon.config.controller`: the robot's 20 parameters, read with tomllib, edited with
tomlkit) and durable writes (:mod:`~loopcal.daemon.config.durable`: atomic replace, the advisory
write lock, symlinks written through).

Imports: the base modules of :mod:`loopcal.daemon` (none yet), calibration/, the standard library
and tomlkit. Everything else in daemon/ may import it.
"""
