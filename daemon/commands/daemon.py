"""``loopcal daemon --config PATH``: the acquisition daemon, as systemd runs it.

Reads the TOML config (every key is described in docs/daemon.md and in
:mod:`loopcal.daemon.recorder.settings`), records until SIGTERM, reloads the config and starts a new
file on SIGHUP, and speaks the systemd notify protocol (READY, STATUS, WATCHDOG) when systemd
gives it a socket. It owns the module (a second loopcal process that opens it is refused)
and listens on its control socket (``[control].socket``) for a technician's session
(``loopcal session``).
"""

from __future__ import annotations

import argparse

from ..arguments import path_argument


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        required=True,
        type=path_argument,
        metavar="PATH",
        help="the daemon's TOML config, e.g. /etc/loopcal/daemon.toml",
    )
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")  # fmt: skip


def run(args: argparse.Namespace) -> int:
    from ..live.health import watch_health
    from ..live.sessions import ControlServer
    from ..live.upkeep import watch_upkeep
    from ..live.view import watch_live
    from ..recorder.engine import Recorder
    from ..recorder.process import run_recorder, setup_logging
    from ..recorder.settings import load_daemon_config

    setup_logging(args.verbose)
    live = control = upkeep = None
    try:
        settings = load_daemon_config(args.config)
        recorder = Recorder(
            settings,
            command=f"loopcal daemon --config {args.config}",
            service=True,
            reload_settings=lambda: load_daemon_config(args.config),
        )
        live = watch_live(recorder, settings.live_listen, health=watch_health(recorder))
        upkeep = watch_upkeep(recorder)
        assert settings.control_socket is not None  # load_daemon_config gives the default
        control = ControlServer(recorder, settings.control_socket, live=live,
                                client_timeout=settings.control_client_timeout_s)  # fmt: skip
        recorder.stop_listeners.append(control.stop_session)
        if upkeep is not None:
            upkeep.hold = control.session_words
    except BaseException:  # bad input (a refused config, a module held elsewhere) or a bug
        if live is not None:
            live.close()
        raise
    try:
        return run_recorder(recorder)
    finally:
        control.close()
        if upkeep is not None:
            upkeep.close()
        if live is not None:
            live.close()
