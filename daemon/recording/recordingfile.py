"""What one file of a recording held and what of it could not be read: :class:`RecordingFile`,
and the one line that says so (:attr:`RecordingFile.warning`).

:class:`~loopcal.daemon.recording.filereader.FileReader` fills it in;
:func:`~loopcal.daemon.recording.reader.read_recordings` lists one per file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..times import span_text, time_or
from .damage import Damage
from .losses import Loss


@dataclass
class RecordingFile:
    """What one file of a recording held, and what of it could not be read.

    One per file in :attr:`Recording.files <loopcal.daemon.recording.reader.Recording.files>`.

    Attributes
    ----------
    path : pathlib.Path
        The file.
    complete : bool
        Closed normally (summary and index present and intact, the index matching the
        chunks).
    scans : int, default 0
        Scans read from it: within the time window, each once, without those a file read
        before it already gave.
    first_stamp_ns : int or None, default None
        The first scan's stamp, ns since the Unix epoch (None: no scan).
    last_stamp_ns : int or None, default None
        The last scan's stamp, ns since the Unix epoch (None: no scan).
    metadata : dict of str to dict of str to str
        Metadata records by name (``loopcal``, ``device``, ``controller_config``), each
        ``{key: value}`` (docs/recording.md).
    note : str, default ""
        How the file was read when it was not closed normally (empty for a complete one).
    damage : list of Damage
        The parts that could not be trusted
        (:class:`~loopcal.daemon.recording.damage.Damage`: byte ranges, what was wrong,
        the time span of the messages they held where known).
    lost : list of Loss
        Scans known to be missing from the file, by counter
        (:class:`~loopcal.daemon.recording.losses.Loss`: counter gaps no ``missed``
        explains, and scans whose views the file holds but not their raw scans).
    lost_unplaced : int, default 0
        Scans missing that :attr:`lost` does not place: the file's statistics record
        counts them (one ``/joint/state`` message per scan written), their counters are
        unknown.
    lost_unknown : str, default ""
        Where an unknown number of scans more may be missing (damage before the first or
        after the last scan known, in a file without trusted statistics); empty when
        :attr:`lost_scans` is the exact count.
    lost_events : int, default 0
        Events known to be missing (by the statistics record, or the message indexes
        after a damaged chunk).
    lost_events_unknown : bool, default False
        Damaged parts may have held events that nothing in the file counts.
    duplicates : int, default 0
        Scans that appeared more than once in the file (each is returned once).
    bad_messages : int, default 0
        Scan blocks or events inside intact chunks that did not decode.
    last_scan_chunk : int, default -1
        Byte offset of the last intact chunk that held scans (-1: none).
    """

    path: Path
    complete: bool
    scans: int = 0
    first_stamp_ns: int | None = None
    last_stamp_ns: int | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    note: str = ""
    damage: list[Damage] = field(default_factory=list)
    lost: list[Loss] = field(default_factory=list)
    lost_unplaced: int = 0
    lost_unknown: str = ""
    lost_events: int = 0
    lost_events_unknown: bool = False
    duplicates: int = 0
    bad_messages: int = 0
    # byte offset of the last intact chunk that held scans (-1: none)
    last_scan_chunk: int = -1

    @property
    def lost_scans(self) -> int:
        """How many scans are known to be missing: :attr:`lost`'s counts and
        :attr:`lost_unplaced`; the exact count unless :attr:`lost_unknown` says where more
        may be."""
        return sum(x.count for x in self.lost) + self.lost_unplaced

    @property
    def intact(self) -> bool:
        """Whether the file read whole (nothing damaged, missing, duplicated or undecodable)."""
        return not (self.damage or self.lost_scans or self.lost_unknown or self.lost_events
                    or self.lost_events_unknown or self.duplicates
                    or self.bad_messages)  # fmt: skip

    @property
    def warning(self) -> str:
        """One line naming the file and what of it was lost, or ``""`` if it read intact.

        The scans missing (how many, exactly or "at least"; counters, epoch and UTC times of
        up to three runs; where an unknown number more may be), the damaged parts, the
        events lost, duplicates dropped and undecodable messages, separated by ``;``.
        """
        if self.intact:
            return ""
        parts = [self._scans_text(), self._damage_text(), self._events_text()]
        if self.duplicates:
            parts.append(f"{self.duplicates} duplicated scan(s) dropped (each kept once)")
        if self.bad_messages:
            parts.append(f"{self.bad_messages} undecodable message(s) skipped")
        return f"{self.path}: " + "; ".join(p for p in parts if p)

    def _scans_text(self) -> str:
        n = self.lost_scans
        if not n and not self.lost_unknown:
            return ""
        if not self.lost_unknown:
            head = f"{n} scan(s) missing"
        else:
            head = f"at least {n} scan(s) missing" if n else "an unknown number of scans missing"
        pieces = []
        if self.lost:
            spans = ", ".join(
                f"counters {x.first}-{x.first + x.count - 1} of epoch {x.epoch} "
                f"({time_or(x.after_ns)} to {time_or(x.before_ns)})"
                for x in self.lost[:3]
            )
            more = f" and {len(self.lost) - 3} more run(s)" if len(self.lost) > 3 else ""
            pieces.append(spans + more)
        if self.lost_unplaced:
            more = f"{self.lost_unplaced} more" if self.lost else f"{self.lost_unplaced}"
            counter = ("loopcal record counts" if self.metadata.get("loopcal", {}).get("views")
                       == "dropped" else "statistics count")  # the views': the record's count
            pieces.append(f"{more} whose counters are unknown (the file's {counter} them)")
        if self.lost_unknown:
            pieces.append(self.lost_unknown)
        return head + (": " + ", ".join(pieces) if pieces else "")

    def _damage_text(self) -> str:
        if not self.damage:
            return ""
        what = "; ".join(f"{d.what} at byte {d.offset}{_span_text(d)}" for d in self.damage[:3])
        more = f"; {len(self.damage) - 3} more" if len(self.damage) > 3 else ""
        cost = " (no scan lost)" if not self.lost_scans and not self.lost_unknown else ""
        return f"{len(self.damage)} damaged part(s): {what}{more}{cost}"

    def _events_text(self) -> str:
        n = self.lost_events
        if self.lost_events_unknown:
            return f"at least {n} event(s) lost" if n else "an unknown number of events lost"
        return f"{n} event(s) lost" if n else ""


def _span_text(d: Damage) -> str:
    span = span_text(d.start_ns, d.end_ns)
    return f" (messages of {span})" if span else ""


__all__ = ["RecordingFile"]
