"""What a reader or a check could not trust in a recording file: one :class:`Damage` per part.

The reader (:mod:`~loopcal.daemon.recording.filereader`) keeps a part's bytes, what was
wrong and its time span; the check of every record (:mod:`~loopcal.daemon.recording.verify`)
also names the record, the topics and the message count, and prints it
(:meth:`Damage.text`, :meth:`Damage.as_json`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..times import span_text, time_json


@dataclass(frozen=True)
class Damage:
    """A part of a file that could not be trusted.

    Attributes
    ----------
    offset : int
        Its first byte in the file.
    length : int
        Bytes it spans (0 when unknown).
    what : str
        What was wrong, for people (e.g. ``"chunk CRC mismatch"``).
    start_ns : int or None, default None
        Log time of the first message it held or described, ns since the Unix epoch, when
        a readable chunk header or index entry says so.
    end_ns : int or None, default None
        Log time of the last, likewise.
    record : str, default ""
        What lies there, as the check of every record names it: ``chunk``, ``message
        index``, ``metadata``, ``header``, ``data end``, ``chunk index``, ``statistics``,
        ``metadata index``, ``summary offset``, ``summary``, ``footer``, ``records`` (bytes
        where no record could be read), ``data section`` (empty: not named).
    topics : tuple of str, default ()
        The topics of the messages it held or described, sorted; empty when nothing says.
    messages : int or None, default None
        How many messages it held or described, when an index or the chunk says.
    """

    offset: int
    length: int
    what: str
    start_ns: int | None = None
    end_ns: int | None = None
    record: str = ""
    topics: tuple[str, ...] = ()
    messages: int | None = None

    def text(self) -> str:
        """One line: ``chunk at byte 3754 (/joint/state, /plate/transform;
        2026-11-18T12:00:01.000Z to 2026-11-18T12:00:01.950Z; 41 messages): CRC mismatch``."""
        parts = [", ".join(self.topics) if self.topics else "topics unknown"]
        span = span_text(self.start_ns, self.end_ns)
        if span:
            parts.append(span)
        if self.messages is not None:
            parts.append(f"{self.messages} message(s)")
        return f"{self.record} at byte {self.offset} ({'; '.join(parts)}): {self.what}"

    def as_json(self) -> dict[str, Any]:
        """The part as a JSON object (``loopcal info --json``, ``loopcal verify --json``)."""
        return {
            "offset": self.offset, "length": self.length, "record": self.record,
            "what": self.what, "topics": list(self.topics) or None,
            "start_utc": time_json(self.start_ns), "end_utc": time_json(self.end_ns),
            "start_ns": self.start_ns, "end_ns": self.end_ns, "messages": self.messages,
        }  # fmt: skip


__all__ = ["Damage"]
