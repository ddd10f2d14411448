"""One module per ``loopcal`` command.

Each module has ``HELP`` (one line), ``add_arguments(parser)`` and ``run(args) -> int``
(the exit status). ``daemon.cli`` only builds the parser from them and dispatches.
"""
