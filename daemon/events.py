"""Events: what happened to the acquisition, as the recording and the log tell it.

An event has a kind (below), a level, a one-line message for people and details for
programs. The acquisition and the recorder raise them; the recorder writes them to the
recording (``/loopcal/events``, and ``/loopcal/log`` for Foxglove's Log panel) and to the
log; the calibration worker reads them back (for example to drop scans next to a gap).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any


class Level(IntEnum):
    """Severity; the numbers are those of Foxglove's ``foxglove.Log`` levels."""

    DEBUG = 1
    INFO = 2
    WARNING = 3
    ERROR = 4


#: every event kind and what it means (docs/recording.md lists the same table)
KINDS: dict[str, str] = {
    "recorder_start": "the recorder started (details: version, pid, resume point)",
    "recorder_stop": "the recorder stopped (details: reason, scans written)",
    "connect": "the DAQ answered after being unreachable (details: url, identity, outage_s)",
    "disconnect": "the DAQ stopped answering or the link failed (details: url, error)",
    "gap": "scans the module made were never received (details: missed, counter64, reason)",
    "restart": "the module restarted: counter back to 0, restart bit set (details: epoch)",
    "overflow": "the module's FIFO overflowed: its oldest scans were lost",
    "rail": "a channel reached or left the rail (details: channel, on)",
    "sensor_fault": "a channel's sensor fault bit rose or fell (details: channel, on)",
    "config_reload": "the configuration was reloaded: SIGHUP, or the controller config file "
    "replaced on disk (details: ok, error, trigger, controller_sha256, provenance)",
    "disk_error": "the recording could not be written (details: path, error)",
    "disk_recovered": "writing works again (details: path, backlog scans, outage_s)",
    "backlog_dropped": "the in-memory backlog overflowed while the disk failed (details: scans)",
    "retention": "an old recording was deleted to stay under the disk budget (details: path)",
    "damaged_recording": "a recording already in the directory is damaged or unreadable: what "
    "of it was lost (the recorder carries on from its last intact scan; details: directory)",
    "views_failed": "the plate's poses could not be computed for a file (the controller "
    "config's parameters give no forward kinematics); its raw scans are recorded "
    "(details: path, error)",
    "offset_drift": "the loops no longer close at the controller config: a sensor's offset "
    "moved (details: sensor 1..4, shift_mm, std_mm, statistic, threshold, margin, poses, "
    "false_alarm)",
    "offset_drift_unattributed": "the loops no longer close at the controller config, and "
    "the poses so far cannot tell which sensor's offset moved (details: candidates, each a "
    "sensor, shift_mm and std_mm; since_ns, statistic, threshold, margin, poses, advice, "
    "false_alarm)",
    "offset_drift_cleared": "that sensor's loops close again (details: sensor, None after an "
    "offset_drift_unattributed; poses)",
    "loops_open": "the loops have not closed at the controller config since the recording "
    "began: at a config loopcal calibrated, a change since that calibration; at one it never "
    "calibrated, the config does not describe the robot, calibrate; no offset_drift follows "
    "(details: poses, since_ns, detected_ns, statistic, threshold, largest_sensor, "
    "largest_shift_mm, calibrated_utc, candidates, false_alarm)",
    "guidance": "the live guidance's verdict while recording (details: enough, reason)",
    "foreign_reader": "another Modbus master takes scans off the module's FIFO: its start "
    "(warning: since, scans taken so far) and its end (details: since_ns, until_ns, taken)",
    "module_held": "the recorder holds the module's lock on this host, or a reload was "
    "refused because another process holds the new module's (details: key, lock, holder)",
    "session_start": "a technician's calibration session began through the daemon's control "
    "socket (details: session, note, asked_by, target_mm, until_enough, duration_s)",
    "offset_change": "upkeep: the loops no longer close at the controller config since a "
    "change it has not fixed yet: the offsets told apart, or the candidates the robot's "
    "motion cannot yet tell apart and the move that would (details: since_ns, names, "
    "candidates, advice, mode)",
    "offset_change_gone": "upkeep: the loops close again, the change it said is gone "
    "(details: since_ns, until_ns)",
    "offsets_uncertain": "upkeep: the controller config (or the proposal pending) knows an "
    "offset too poorly to vouch for the threshold (3 std reach it): fixes of single offsets "
    "from motion that cannot tell the four apart carried the others' errors into them; "
    "calibrate with loopcal session (details: std, threshold_mm)",
    "upkeep_reset": "the upkeep's kept record (its baseline and any change in progress) "
    "could not be taken up: damaged, or of another format version; set aside, and the upkeep "
    "starts over from the controller config's own calibration (details: path, aside, error)",
    "recalibration_proposed": "upkeep found an offset changed and identified it from the "
    "robot's motion, every gate passed: a complete config written beside the controller "
    "config (.proposed) for a person to apply (details: path, values, std, scans_std, "
    "shift_mm, since_ns, window_since_ns, window_until_ns, scans, gates)",
    "recalibrated": "upkeep in write mode wrote such a change into the controller config, the "
    "previous version kept (details: path, previous, values, std, scans_std, shift_mm, "
    "since_ns, window_since_ns, window_until_ns, scans, gates)",
    "recalibration_withdrawn": "later scans contradict a pending proposal: it is renamed aside "
    "(details: path, aside, names, since_ns)",
    "recalibration_refused": "upkeep saw a change the robot's motion does not identify, or "
    "could not write what it identified (details: names, since_ns, refusal)",
    "session_end": "that session ended: enough, duration, stopped, abandoned or the daemon "
    "stopping (details: session, reason, since_ns, until_ns, scans, enough, std)",
}


@dataclass(frozen=True)
class Event:
    """One event.

    stamp_ns: when it happened, ns since the Unix epoch (UTC).
    kind: one of :data:`KINDS`.
    level: severity.
    message: one line for people.
    details: JSON-serialisable facts for programs.
    """

    stamp_ns: int
    kind: str
    level: Level
    message: str
    details: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown event kind {self.kind!r}")

    def to_json(self) -> dict[str, Any]:
        """The ``loopcal.Event`` message (see :mod:`loopcal.daemon.recording`)."""
        sec, nsec = divmod(int(self.stamp_ns), 1_000_000_000)
        return {
            "timestamp": {"sec": sec, "nsec": nsec},
            "kind": self.kind,
            "level": int(self.level),
            "message": self.message,
            "details": self.details,
        }

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> Event:
        ts = obj["timestamp"]
        return cls(
            stamp_ns=int(ts["sec"]) * 1_000_000_000 + int(ts["nsec"]),
            kind=str(obj["kind"]),
            level=Level(int(obj["level"])),
            message=str(obj["message"]),
            details=dict(obj.get("details") or {}),
        )

    def log(self, logger: logging.Logger) -> None:
        """Write the event as one log line at its level."""
        extra = f" {json.dumps(self.details, sort_keys=True)}" if self.details else ""
        logger.log(_LOG_LEVELS[self.level], "%s: %s%s", self.kind, self.message, extra)


_LOG_LEVELS = {
    Level.DEBUG: logging.DEBUG,
    Level.INFO: logging.INFO,
    Level.WARNING: logging.WARNING,
    Level.ERROR: logging.ERROR,
}
