"""The recorder's settings: from ``loopcal record``'s options or ``loopcal daemon``'s TOML.

The daemon's config file (every key; docs/daemon.md says the same)::

    [daq]
    url = "modbus-tcp://192.168.1.50:502?unit=1"   # required: the driver URL
    timeout = 0.1            # s without an answer before a read fails (datasheet: 0.1)
    read_period = 0.2        # s between FIFO reads (Modbus); without a FIFO it polls each scan

    [recording]
    directory = "/var/lib/loopcal/recordings"      # required: where recordings go
    flush_period = 1.0       # s between flushes to the disk (0.05 .. 1)
    rotate_seconds = 3600    # start a new file after this long (>= 1)
    rotate_size = "256 MiB"  # ... or once a file is this big (bytes, or "N KiB|MiB|GiB")
    disk_budget = "20 GiB"   # delete the oldest recordings to stay under this; 0: keep all
    max_backlog_scans = 500000  # scans kept in memory while the disk refuses them
    compact = true           # rewrite closed files with large chunks for fast reading

    [controller]
    config = "/etc/loopcal/controller/controller.toml"        # the controller config the poses use

    [health]
    enabled = true           # watch loop closure and raise offset_drift events
    false_alarm = 1e-8       # probability per still pose of an alarm when nothing moved

    [metrics]
    listen = "127.0.0.1:9464"  # serve Prometheus metrics on http://HOST:PORT/metrics (off
                               # unless given)

Unknown tables or keys and bad values are refused with a message naming the key.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from loopcal.drivers import driver_for_url, ldq412

_SIZE_RE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(B|KiB|MiB|GiB|TiB|kB|MB|GB|TB)?\s*$")
_UNITS = {None: 1, "B": 1, "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30, "TiB": 1 << 40,
          "kB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12}  # fmt: skip


_MAX_SIZE = float(1 << 62)
#: the most scans the backlog may hold in memory (about 560 MB)
MAX_BACKLOG_SCANS = 10_000_000


class SettingsError(ValueError):
    """A bad setting; the message names the file (if any) and the key."""


@dataclass(frozen=True)
class RecorderSettings:
    """Everything the recorder needs.

    daq_url: driver URL. timeout_s: answer timeout. read_period_s: s between FIFO reads.
    directory: where recordings go. flush_period_s: s between flushes (at most 1, so a
    crash loses at most that much). rotate_seconds, rotate_bytes: start a new file after
    this long or this big. disk_budget_bytes: delete the oldest recordings to stay under it
    (0: keep all). max_backlog_scans: scans kept in memory while the disk refuses them.
    controller_config: the controller config file, or None for the reference geometry.
    duration_s: stop after this long (``loopcal record --duration``), or None.
    metrics_listen: "HOST:PORT" to serve Prometheus metrics on (None: off). compact: rewrite
    every closed (rotated) file with large chunks in the background
    (:mod:`loopcal.daemon.recording.compact`).
    health: watch loop closure (:mod:`loopcal.daemon.live.health`); health_false_alarm: its
    false-alarm probability per still pose.
    """

    daq_url: str
    directory: Path
    timeout_s: float = ldq412.HOST_TIMEOUT_S
    read_period_s: float = 0.2
    flush_period_s: float = 1.0
    rotate_seconds: float = 3600.0
    rotate_bytes: int = 256 << 20
    disk_budget_bytes: int = 0
    max_backlog_scans: int = 500_000
    controller_config: Path | None = None
    duration_s: float | None = None
    health: bool = True
    health_false_alarm: float = 1e-8
    compact: bool = True
    metrics_listen: str | None = None

    def checked(self, where: str = "") -> RecorderSettings:
        """Validate every value; raises SettingsError naming the key."""
        prefix = f"{where}: " if where else ""

        def bad(key: str, why: str) -> SettingsError:
            return SettingsError(f"{prefix}{_KEY_NAMES.get(key, key)}: {why}")

        try:
            driver_for_url(self.daq_url)
        except ValueError as exc:
            raise bad("daq_url", str(exc)) from None
        _positive(self.timeout_s, "timeout_s", bad, hi=10.0)
        _positive(self.read_period_s, "read_period_s", bad, hi=5.0)
        _positive(self.flush_period_s, "flush_period_s", bad, lo=0.05, hi=1.0)
        _positive(self.rotate_seconds, "rotate_seconds", bad, lo=1.0)
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
        if self.duration_s is not None:
            _positive(self.duration_s, "duration_s", bad)
        if str(self.directory) == "":
            raise bad("directory", "is empty")
        if not isinstance(self.health, bool):
            raise bad("health", f"must be true or false, got {self.health!r}")
        if not isinstance(self.compact, bool):
            raise bad("compact", f"must be true or false, got {self.compact!r}")
        fa = self.health_false_alarm
        if isinstance(fa, bool) or not isinstance(fa, (int, float)) or not 0 < fa < 1e-2:
            raise bad("health_false_alarm", f"must be a probability in (0, 0.01), got {fa!r}")
        if self.metrics_listen is not None:
            try:
                parse_listen(self.metrics_listen)
            except ValueError as exc:
                raise bad("metrics_listen", str(exc)) from None
        return self


_KEY_NAMES = {
    "daq_url": "[daq].url",
    "timeout_s": "[daq].timeout",
    "read_period_s": "[daq].read_period",
    "directory": "[recording].directory",
    "flush_period_s": "[recording].flush_period",
    "rotate_seconds": "[recording].rotate_seconds",
    "rotate_bytes": "[recording].rotate_size",
    "disk_budget_bytes": "[recording].disk_budget",
    "max_backlog_scans": "[recording].max_backlog_scans",
    "compact": "[recording].compact",
    "controller_config": "[controller].config",
    "duration_s": "--duration",
    "health": "[health].enabled",
    "health_false_alarm": "[health].false_alarm",
    "metrics_listen": "[metrics].listen",
}


def _positive(value: Any, key: str, bad, *, lo: float | None = None, hi: float = math.inf) -> None:
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


#: [table] -> {key: (field, converter)}
_SCHEMA: dict[str, dict[str, str]] = {
    "daq": {"url": "daq_url", "timeout": "timeout_s", "read_period": "read_period_s"},
    "recording": {
        "directory": "directory",
        "flush_period": "flush_period_s",
        "rotate_seconds": "rotate_seconds",
        "rotate_size": "rotate_bytes",
        "disk_budget": "disk_budget_bytes",
        "max_backlog_scans": "max_backlog_scans",
        "compact": "compact",
    },
    "controller": {"config": "controller_config"},
    "health": {"enabled": "health", "false_alarm": "health_false_alarm"},
    "metrics": {"listen": "metrics_listen"},
}
_REQUIRED = {("daq", "url"), ("recording", "directory")}


def load_daemon_config(path: str | os.PathLike) -> RecorderSettings:
    """Read and validate ``loopcal daemon``'s TOML config (see the module docstring)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise SettingsError(f"{p}: cannot read the config: {exc.strerror or exc}") from None
    try:
        doc = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise SettingsError(f"{p}: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise SettingsError(f"{p}: not valid TOML: {exc}") from None
    fields: dict[str, Any] = {}
    for table, value in doc.items():
        if table not in _SCHEMA:
            raise SettingsError(
                f"{p}: unknown table or key {table!r} (known tables: "
                f"{', '.join(f'[{t}]' for t in _SCHEMA)})"
            )
        if not isinstance(value, dict):
            raise SettingsError(f"{p}: {table!r} must be a table [{table}]")
        for key, v in value.items():
            if key not in _SCHEMA[table]:
                raise SettingsError(
                    f"{p}: [{table}].{key}: unknown key (known: {', '.join(_SCHEMA[table])})"
                )
            field = _SCHEMA[table][key]
            fields[field] = _convert(p, table, key, field, v)
    for table, key in sorted(_REQUIRED):
        if _SCHEMA[table][key] not in fields:
            raise SettingsError(f"{p}: [{table}].{key} is required")
    return RecorderSettings(**fields).checked(str(p))


def _convert(p: Path, table: str, key: str, field: str, v: Any) -> Any:
    where = f"{p}: [{table}].{key}"
    if field in ("daq_url", "metrics_listen"):
        if not isinstance(v, str):
            raise SettingsError(f"{where}: must be a string, got {v!r}")
        return v
    if field in ("directory", "controller_config"):
        if not isinstance(v, str) or not v or "\0" in v:
            raise SettingsError(f"{where}: must be a path (a non-empty string), got {v!r}")
        path = Path(v)
        if not path.is_absolute():
            path = (p.parent / path).resolve()  # relative to the config file
        return path
    if field in ("rotate_bytes", "disk_budget_bytes"):
        try:
            return parse_size(v)
        except ValueError as exc:
            raise SettingsError(f"{where}: {exc}") from None
    if field in ("health", "compact"):
        if not isinstance(v, bool):
            raise SettingsError(f"{where}: must be true or false, got {v!r}")
        return v
    if field == "health_false_alarm":
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise SettingsError(f"{where}: must be a probability, got {v!r}")
        return float(v)
    if field == "max_backlog_scans":
        if isinstance(v, bool) or not isinstance(v, int):
            raise SettingsError(f"{where}: must be an integer, got {v!r}")
        return v
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise SettingsError(f"{where}: must be a number of seconds, got {v!r}")
    return float(v)


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
