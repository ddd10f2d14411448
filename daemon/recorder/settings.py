"""The recorder's settings, declared once: every setting's TOML key, ``loopcal record``
option, default, help and checks come from :class:`RecorderSettings`' fields.

:func:`load_daemon_config` reads ``loopcal daemon``'s TOML config; :func:`add_options` and
:func:`settings_from_args` are ``loopcal record``'s options for the same settings;
:func:`markdown_table` is docs/daemon.md's table of keys (a test keeps the two the same).
Unknown tables or keys and bad values are refused with a message naming the key as the
user wrote it (``[recording].rotate_size`` in a config, ``--rotate-size`` on the command
line).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import tomllib
from collections.abc import Callable
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from typing import Any

from loopcal.drivers import driver_for_url, ldq412
from loopcal.drivers.pacing import FIFO_READ_PERIOD_S

from ..arguments import duration_argument, path_argument
from ..defaults import (
    FALSE_ALARM,
    FALSE_ALARM_MAX,
    UPKEEP_SEGMENT_S,
    UPKEEP_TARGET_MM,
    UPKEEP_THRESHOLD_MM,
)
from .ownership import runtime_directory

_SIZE_RE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(B|KiB|MiB|GiB|TiB|kB|MB|GB|TB)?\s*$")
_UNITS = {None: 1, "B": 1, "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30, "TiB": 1 << 40,
          "kB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12}  # fmt: skip


_MAX_SIZE = float(1 << 62)
#: the daemon's control socket's name in the runtime directory (the default of [control].socket)
CONTROL_SOCKET_NAME = "control.sock"
#: the most scans the backlog may hold in memory (about 560 MB)
MAX_BACKLOG_SCANS = 10_000_000
#: s between two lines saying why the module cannot be reached, while it cannot (the
#: acquisition's default too)
UNREACHABLE_REPORT_S = 30.0

class SettingsError(ValueError):
    """A bad setting. ``field`` is the :class:`RecorderSettings` field at fault (None when
    no one key is), ``detail`` what is wrong, ``where`` the config file (if any); the
    message names the key as a config writes it (:meth:`named` names it otherwise)."""

    def __init__(self, detail: str, field: str | None = None, where: str = "") -> None:
        self.detail, self.field, self.where = detail, field, where
        super().__init__(self.named(config_key))

    def named(self, name: Callable[[str], str]) -> str:
        """The message, with the key named by ``name(field)`` (:func:`config_key`,
        :func:`option_name`)."""
        prefix = f"{self.where}: " if self.where else ""
        key = f"{name(self.field)}: " if self.field else ""
        return prefix + key + self.detail


@dataclass(frozen=True)
class Setting:
    """How a setting is written and checked.

    kind: url, path, seconds, size, count, switch, probability, listen, days, mm or choice
    (one of ``choices``). help: what it
    means (the option's help and the docs' table). key: ``[table].key`` in the daemon's
    config (None: command line only). option: ``loopcal record``'s option (None: config
    only; for a switch, the option that turns it off). shown_default: the default as the
    docs write it, if not the value itself. lo, hi: bounds of a number of seconds (lo None:
    > 0). metavar: the option's placeholder."""

    kind: str
    help: str
    key: str | None = None
    option: str | None = None
    shown_default: str | None = None
    lo: float | None = None
    hi: float = math.inf
    metavar: str | None = None
    choices: tuple[str, ...] = ()


def _setting(default: Any = MISSING, **spec: Any) -> Any:
    return field(default=default, metadata={"setting": Setting(**spec)})


@dataclass(frozen=True)
class RecorderSettings:
    """Everything the recorder needs; each field's :class:`Setting` says how it is written
    (docs/daemon.md's table is :func:`markdown_table`). Units: s, bytes, scans."""

    daq_url: str = _setting(
        kind="url", key="[daq].url", option="--daq", metavar="URL",
        help="driver URL, e.g. modbus-tcp://192.168.1.50:502?unit=1, "
             "modbus-rtu:///dev/ttyUSB0?baud=115200&unit=1 or "
             "ascii:///dev/ttyS0?baud=115200&addr=01&checksum=0; a serial line behind a "
             "serial device server is modbus-rtu://HOST:PORT?unit=1 or "
             "ascii://HOST:PORT?addr=01 (docs/daq.md, \"Driver URLs\", lists every "
             "parameter)")  # fmt: skip
    directory: Path = _setting(
        kind="path", key="[recording].directory", option="--out", metavar="DIR",
        help="where recordings go; created if missing; in a config, a relative path is "
             "relative to the config file")  # fmt: skip
    timeout_s: float = _setting(
        ldq412.HOST_TIMEOUT_S, kind="seconds", key="[daq].timeout", option="--timeout", hi=10.0,
        help="seconds without an answer before a read fails (the datasheet's 100 ms; a "
             "Modbus FIFO read, whose scans already left the module, waits up to 2.5 s); at "
             "most 10")  # fmt: skip
    read_period_s: float = _setting(
        FIFO_READ_PERIOD_S, kind="seconds", key="[daq].read_period", option="--read-period",
        hi=5.0, help="seconds between FIFO reads; at most 5 (the FIFO holds 12.8 s at 20 Hz); "
             "without a FIFO the module is polled once a scan")  # fmt: skip
    unreachable_report_s: float = _setting(
        UNREACHABLE_REPORT_S, kind="seconds", key="[daq].unreachable_report",
        option="--unreachable-report", lo=1.0, hi=3600.0,
        help="while the module cannot be reached, say why every this many seconds: one "
             "WARNING line with the cause and what to do, as loopcal probe says it; 1 to "
             "3600")  # fmt: skip
    flush_period_s: float = _setting(
        1.0, kind="seconds", key="[recording].flush_period", option="--flush-period",
        lo=0.05, hi=1.0,
        help="seconds between flushes to disk, 0.05 to 1: what a crash can lose at "
             "most")  # fmt: skip
    rotate_seconds: float = _setting(
        3600.0, kind="seconds", key="[recording].rotate_seconds", option="--rotate-seconds",
        lo=1.0, help="a new file after this many seconds (at least 1)")  # fmt: skip
    rotate_bytes: int = _setting(
        256 << 20, kind="size", key="[recording].rotate_size", option="--rotate-size",
        shown_default="256 MiB",
        help='a new file once this big: bytes, or a text such as "64 MiB", "2 GB" (at least '
             "64 KiB)")  # fmt: skip
    disk_budget_bytes: int = _setting(
        0, kind="size", key="[recording].disk_budget", option="--disk-budget",
        shown_default="0: keep all",
        help="delete the oldest recordings to stay under this; at least two files' "
             "worth")  # fmt: skip
    max_backlog_scans: int = _setting(
        500_000, kind="count", key="[recording].max_backlog_scans",
        option="--max-backlog-scans",
        help="scans kept in memory while the disk refuses writes (about 7 hours at 20 Hz, "
             "30 MB); the oldest are dropped beyond, with an event")  # fmt: skip
    compact: bool = _setting(
        True, kind="switch", key="[recording].compact", option="--no-compact",
        help="rewrite each closed file in chunks of a minute, for fast reading, in a child "
             "process (loopcal compact) so that its memory goes with it (off: the "
             "one-second chunks stay as written)")  # fmt: skip
    keep_views_days: float = _setting(
        7.0, kind="days", key="[recording].keep_views_days", option="--keep-views-days",
        help="compaction leaves out the per-scan views (/joint/state, /plate/transform) of "
             "files started this many days ago or more: every raw scan and event stays, about "
             "5 bytes a scan against 120, and loopcal export makes the views again; 0: at "
             "once, inf: never (needs [recording].compact)")  # fmt: skip
    controller_config: Path | None = _setting(
        None, kind="path", key="[controller].config", option="--controller-config",
        shown_default="none",
        help="the controller config for the recorded poses and loop-closure health "
             "(loopcal init-config writes one); without it, the reference geometry")  # fmt: skip
    duration_s: float | None = _setting(
        None, kind="seconds", option="--duration", shown_default="until SIGINT/SIGTERM",
        help="stop after this long by the host's clock (the wall time; an emulated module "
             "running X times as fast makes X times as many scans meanwhile)")  # fmt: skip
    health: bool = _setting(
        True, kind="switch", key="[health].enabled", option="--no-health",
        help="watch loop closure and raise offset_drift events")  # fmt: skip
    health_false_alarm: float = _setting(
        FALSE_ALARM, kind="probability", key="[health].false_alarm", shown_default="1e-8",
        help="probability per still pose of an alarm when nothing moved, below 0.01")  # fmt: skip
    metrics_listen: str | None = _setting(
        None, kind="listen", key="[metrics].listen", option="--metrics",
        metavar="HOST:PORT", shown_default="off",
        help="serve Prometheus metrics on http://HOST:PORT/metrics, e.g. "
             "127.0.0.1:9464")  # fmt: skip
    control_socket: Path | None = _setting(
        None, kind="path", key="[control].socket",
        shown_default="control.sock in the runtime directory (/run/loopcal)",
        help="the daemon's control socket, a unix socket that loopcal session asks for a "
             "technician's session through (owner and group may connect: the loopcal "
             "group); loopcal daemon only")  # fmt: skip
    control_client_timeout_s: float = _setting(
        30.0, kind="seconds", key="[control].client_timeout", lo=1.0, hi=3600.0,
        help="a session whose client has said nothing for this long (a closed laptop, a "
             "dropped SSH) ends by itself, marked abandoned")  # fmt: skip
    upkeep_mode: str | None = _setting(
        None, kind="choice", key="[upkeep].mode", option="--upkeep",
        choices=("off", "propose", "write"),
        shown_default='"propose" with a controller config, else "off"',
        help="recalibrate what changed from the robot's own motion: off; propose (a "
             "complete config written beside the controller config, with .proposed appended, "
             "for a person to apply: loopcal upkeep apply); write (straight into the "
             "controller config, the previous version kept); docs/calibration.md")  # fmt: skip
    upkeep_target_mm: float = _setting(
        UPKEEP_TARGET_MM, kind="mm", key="[upkeep].target_mm", lo=0.001, hi=1.0,
        help="the standard deviation a recalibrated offset must reach, mm")  # fmt: skip
    upkeep_threshold_mm: float = _setting(
        UPKEEP_THRESHOLD_MM, kind="mm", key="[upkeep].threshold_mm", lo=0.01, hi=10.0,
        help="the smallest change of an offset upkeep acts on, mm")  # fmt: skip
    upkeep_min_interval_s: float = _setting(
        600.0, kind="seconds", key="[upkeep].min_interval", lo=10.0, hi=30 * 86400.0,
        help="the least time between two recalibrations of an offset that creeps (it goes "
             "on the same way, little by little, after a fix), s; a step, a swapped sensor, "
             "is fixed at once")  # fmt: skip
    upkeep_segment_s: float = _setting(
        UPKEEP_SEGMENT_S, kind="seconds", key="[upkeep].segment", lo=5.0, hi=600.0,
        help="how much of the scans the upkeep tests at a time, s: a change stands after "
             "two segments that moved, so shorter ones see it sooner, from fewer scans "
             "each (a segment of fewer than 100 usable scans tells nothing)")  # fmt: skip
    live_listen: str | None = _setting(
        None, kind="listen", key="[live].listen", option="--live", metavar="HOST:PORT",
        shown_default="off",
        help="serve the session live to Foxglove (WebSocket, read-only) on HOST:PORT, e.g. "
             "127.0.0.1:8765 (docs/tools.md: connecting, and what another address "
             "exposes)")  # fmt: skip

    def checked(self, where: str = "") -> RecorderSettings:
        """Validate every value; raises SettingsError naming the key."""

        def bad(key: str, why: str) -> SettingsError:
            return SettingsError(why, key, where)

        try:
            driver_for_url(self.daq_url)
        except ValueError as exc:
            raise bad("daq_url", str(exc)) from None
        for name, spec in SETTINGS.items():
            value = getattr(self, name)
            if spec.kind == "seconds" and value is not None:
                _seconds(value, name, bad, lo=spec.lo, hi=spec.hi)
            elif spec.kind == "switch" and not isinstance(value, bool):
                raise bad(name, f"must be true or false, got {value!r}")
            elif spec.kind == "choice" and value is not None and value not in spec.choices:
                raise bad(name, f"must be one of {', '.join(spec.choices)}, got {value!r}")
            elif spec.kind == "mm" and (isinstance(value, bool)
                                        or not isinstance(value, (int, float))
                                        or not spec.lo <= value <= spec.hi):  # fmt: skip
                raise bad(name, f"must be a length in {spec.lo:g}..{spec.hi:g} mm, got {value!r}")
            elif spec.kind == "days" and (isinstance(value, bool)
                                          or not isinstance(value, (int, float))
                                          or not value >= 0):  # fmt: skip
                raise bad(name, f"must be a number of days >= 0 (inf: never), got {value!r}")
        if not isinstance(self.rotate_bytes, int) or self.rotate_bytes < 64 << 10:
            raise bad("rotate_bytes", f"must be at least 64 KiB, got {self.rotate_bytes!r}")
        if not isinstance(self.disk_budget_bytes, int) or self.disk_budget_bytes < 0:
            raise bad("disk_budget_bytes", f"must be >= 0 bytes, got {self.disk_budget_bytes!r}")
        if self.disk_budget_bytes and self.disk_budget_bytes < 2 * self.rotate_bytes:
            raise bad(
                "disk_budget_bytes",
                f"{self.disk_budget_bytes} bytes is less than two files of rotate_size "
                f"({self.rotate_bytes} bytes); raise it or lower rotate_size",
            )
        if (not isinstance(self.max_backlog_scans, int)
                or not 1000 <= self.max_backlog_scans <= MAX_BACKLOG_SCANS):  # fmt: skip
            raise bad("max_backlog_scans", f"must be an integer in 1000..{MAX_BACKLOG_SCANS}, "
                      f"got {self.max_backlog_scans!r}")  # fmt: skip
        if str(self.directory) == "":
            raise bad("directory", "is empty")
        fa = self.health_false_alarm
        if (isinstance(fa, bool) or not isinstance(fa, (int, float))
                or not 0 < fa < FALSE_ALARM_MAX):  # fmt: skip
            raise bad("health_false_alarm",
                      f"must be a probability in (0, {FALSE_ALARM_MAX:g}), got {fa!r}")  # fmt: skip
        for name in ("metrics_listen", "live_listen"):
            if getattr(self, name) is not None:
                try:
                    parse_listen(getattr(self, name))
                except ValueError as exc:
                    raise bad(name, str(exc)) from None
        return self


#: field name -> its Setting, in declaration order
SETTINGS: dict[str, Setting] = {f.name: f.metadata["setting"] for f in fields(RecorderSettings)}
#: field name -> its default (fields with none are required)
DEFAULTS: dict[str, Any] = {
    f.name: f.default for f in fields(RecorderSettings) if f.default is not MISSING
}


def config_key(name: str) -> str:
    """How a daemon config names field ``name`` (``[recording].rotate_size``), or the
    option for a command-line-only setting."""
    spec = SETTINGS[name]
    return spec.key or spec.option or name


def option_name(name: str) -> str:
    """How ``loopcal record`` names field ``name`` (``--rotate-size``), or the config key
    for a config-only setting."""
    spec = SETTINGS[name]
    return spec.option or spec.key or name


def _seconds(value: Any, key: str, bad, *, lo: float | None = None, hi: float = math.inf) -> None:
    """A number of seconds, > 0 (or >= lo if given) and <= hi."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise bad(key, f"must be a number of seconds, got {value!r}")
    low_ok = value > 0 if lo is None else value >= lo
    if not low_ok or value > hi:
        rng = "> 0" if lo is None else f">= {lo:g}"
        if hi != math.inf:
            rng += f" and <= {hi:g}"
        raise bad(key, f"must be {rng} s, got {value!r}")


def parse_size(value: Any) -> int:
    """Bytes from an integer or a text such as ``"256 MiB"``; raises ValueError."""
    if isinstance(value, bool):
        raise ValueError(f"{value!r} is not a size")
    if isinstance(value, int):
        return value
    if isinstance(value, str):
        m = _SIZE_RE.match(value)
        if m:
            size = float(m.group(1)) * _UNITS[m.group(2)]
            if size < _MAX_SIZE:
                return int(size)
            raise ValueError(f"{value!r} is more than any disk holds")
    raise ValueError(f'{value!r} is not a size (bytes, or e.g. "256 MiB", "20 GiB")')


def _tables() -> dict[str, dict[str, str]]:
    """[table] -> {key: field}, from the settings' keys."""
    tables: dict[str, dict[str, str]] = {}
    for name, spec in SETTINGS.items():
        if spec.key is not None:
            table, key = spec.key[1:].split("].")
            tables.setdefault(table, {})[key] = name
    return tables


def load_daemon_config(path: str | os.PathLike) -> RecorderSettings:
    """Read and validate ``loopcal daemon``'s TOML config (keys: :data:`SETTINGS`)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise SettingsError(f"cannot read the config: {exc.strerror or exc}", where=str(p)) \
            from None  # fmt: skip
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise SettingsError("not UTF-8 text", where=str(p)) from None
    except tomllib.TOMLDecodeError as exc:
        raise SettingsError(f"not valid TOML: {exc}", where=str(p)) from None
    schema = _tables()
    values: dict[str, Any] = {}
    for table, value in doc.items():
        if table not in schema:
            raise SettingsError(
                f"unknown table or key {table!r} (known tables: "
                f"{', '.join(f'[{t}]' for t in schema)})", where=str(p)
            )  # fmt: skip
        if not isinstance(value, dict):
            raise SettingsError(f"{table!r} must be a table [{table}]", where=str(p))
        for key, v in value.items():
            if key not in schema[table]:
                raise SettingsError(
                    f"[{table}].{key}: unknown key (known: {', '.join(schema[table])})",
                    where=str(p),
                )
            name = schema[table][key]
            values[name] = _convert(p, name, v)
    for name in SETTINGS:
        if name not in DEFAULTS and name not in values:
            raise SettingsError(f"{config_key(name)} is required", where=str(p))
    values.setdefault("control_socket", runtime_directory() / CONTROL_SOCKET_NAME)
    return RecorderSettings(**values).checked(str(p))


def _convert(p: Path, name: str, v: Any) -> Any:
    """A TOML value as field ``name`` holds it (type errors here; ranges in checked())."""
    kind = SETTINGS[name].kind

    def bad(why: str) -> SettingsError:
        return SettingsError(why, name, str(p))

    if kind in ("url", "listen"):
        if not isinstance(v, str):
            raise bad(f"must be a string, got {v!r}")
        return v
    if kind == "path":
        if not isinstance(v, str) or not v or "\0" in v:
            raise bad(f"must be a path (a non-empty string), got {v!r}")
        path = Path(v)
        if not path.is_absolute():
            path = (p.parent / path).resolve()  # relative to the config file
        return path
    if kind == "size":
        try:
            return parse_size(v)
        except ValueError as exc:
            raise bad(str(exc)) from None
    if kind == "switch":
        if not isinstance(v, bool):
            raise bad(f"must be true or false, got {v!r}")
        return v
    if kind == "count":
        if isinstance(v, bool) or not isinstance(v, int):
            raise bad(f"must be an integer, got {v!r}")
        return v
    if kind == "choice":
        if v not in SETTINGS[name].choices:
            raise bad(f"must be one of {', '.join(SETTINGS[name].choices)}, got {v!r}")
        return v
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise bad(f"must be {_NUMBERS[kind]}, got {v!r}")
    return float(v)


#: what a number of each kind is, in words (a TOML value of the wrong type names it)
_NUMBERS = {"probability": "a probability", "mm": "a length in mm",
            "days": "a number of days (inf: never)", "seconds": "a number of seconds"}  # fmt: skip


def _size_option(text: str) -> int:
    try:
        return parse_size(int(text) if text.isdigit() else text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


_OPTION_TYPES: dict[str, Callable[[str], Any]] = {
    "url": str, "listen": str, "path": path_argument, "seconds": duration_argument,
    "size": _size_option,
    "count": int, "probability": float, "days": float, "mm": float,
}  # fmt: skip


def add_options(p: argparse.ArgumentParser) -> None:
    """``loopcal record``'s options for every setting that has one (dest: the field)."""
    for name, spec in SETTINGS.items():
        if spec.option is None:
            continue
        if spec.kind == "switch":
            p.add_argument(spec.option, dest=name, action="store_false",
                           help=f"switch off the default: {spec.help}")  # fmt: skip
            continue
        required = name not in DEFAULTS
        shown = "" if required else f" (default {shown_default(name)})"
        if spec.kind == "choice":
            p.add_argument(spec.option, dest=name, choices=spec.choices, default=DEFAULTS[name],
                           help=spec.help + shown)  # fmt: skip
            continue
        p.add_argument(spec.option, dest=name, required=required, type=_OPTION_TYPES[spec.kind],
                       default=DEFAULTS.get(name), metavar=spec.metavar or _metavar(spec.kind),
                       help=spec.help + shown)  # fmt: skip


def _metavar(kind: str) -> str:
    return {"seconds": "D", "size": "SIZE", "count": "N", "path": "PATH",
            "days": "DAYS"}.get(kind, "VALUE")  # fmt: skip


def settings_from_args(args: argparse.Namespace) -> RecorderSettings:
    """The settings :func:`add_options` parsed (checked; a SettingsError names the field)."""
    return RecorderSettings(
        **{name: getattr(args, name) for name, spec in SETTINGS.items() if spec.option}
    ).checked()


def shown_default(name: str) -> str:
    """Field ``name``'s default as the docs and the help write it."""
    spec = SETTINGS[name]
    if name not in DEFAULTS:
        return "required"
    if spec.shown_default is not None:
        return spec.shown_default
    value = DEFAULTS[name]
    return str(value).lower() if isinstance(value, bool) else f"{value:g}" \
        if isinstance(value, float) else str(value)  # fmt: skip


def markdown_table() -> str:
    """docs/daemon.md's table of the daemon config's keys (and loopcal record's options)."""
    rows = ["| key | `loopcal record` | default | meaning |", "|---|---|---|---|"]
    for name, spec in SETTINGS.items():
        if spec.key is None:
            continue
        option = f"`{spec.option}`" if spec.option else "-"
        rows.append(f"| `{spec.key}` | {option} | {shown_default(name)} | {spec.help} |")
    return "\n".join(rows) + "\n"


_LISTEN_RE = re.compile(
    r"^(?:\[(?P<v6>[0-9A-Fa-f:.]+)\]|(?P<host>[A-Za-z0-9.-]+)):(?P<port>\d{1,5})\Z"
)


def parse_listen(text: str) -> tuple[str, int]:
    """("host", port) from ``HOST:PORT`` (``[::1]:9464`` for IPv6). Raises ValueError."""
    m = _LISTEN_RE.match(text.strip()) if isinstance(text, str) else None
    if not m:
        raise ValueError(f"{text!r} is not HOST:PORT (e.g. 127.0.0.1:9464 or [::1]:9464)")
    port = int(m["port"])
    if not 1 <= port <= 65535:
        raise ValueError(f"{text!r}: port {port} is outside 1..65535")
    return (m["v6"] or m["host"]), port
