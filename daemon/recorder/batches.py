"""What acquisition hands on (:mod:`loopcal.daemon.recorder.acquisition`): the module it talks to,
batches of scan rows and events, the point a new recorder carries on from, and the counters
the status line and the metrics read. Imports only the shared scans and events."""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np

from ..events import Event
from .clockmap import StampFloor


@dataclass(frozen=True)
class DeviceInfo:
    """What the module at the URL said it is, at connect."""

    url: str
    model: str
    firmware: str
    serial: int | None
    scan_rate_hz: int
    has_fifo: bool

    def as_metadata(self) -> dict[str, str]:
        return {
            "url": self.url,
            "model": self.model,
            "firmware": self.firmware,
            "serial": "" if self.serial is None else str(self.serial),
            "scan_rate_hz": str(self.scan_rate_hz),
            "fifo": str(self.has_fifo).lower(),
        }


@dataclass(frozen=True)
class ResumePoint:
    """The last scan already recorded (where a new recorder carries on). floor: the last
    stamp handed on, for an acquisition that carries on in the same process (a reload that
    reopens the DAQ): its stamps come after it. A recorder started again opens a new file,
    whatever the stamps of the last one, so from a recording it is None."""

    epoch: int
    counter64: int
    time64_us: int
    serial: int | None
    floor: StampFloor | None = None

    @classmethod
    def from_row(cls, row: np.void, device_metadata: dict[str, str]) -> ResumePoint:
        serial = device_metadata.get("serial") or None
        return cls(
            int(row["epoch"]),
            int(row["counter64"]),
            int(row["time64_us"]),
            int(serial) if serial is not None else None,
        )


@dataclass
class Batch:
    """What one read produced: scan rows (SCAN_DTYPE, oldest first) and events."""

    rows: np.ndarray
    events: list[Event]
    device: DeviceInfo | None


@dataclass
class AcquisitionStats:
    """Counters for the status line and the benchmarks (read by other threads)."""

    scans: int = 0
    missed: int = 0
    gaps: int = 0
    restarts: int = 0
    reads: int = 0
    read_errors: int = 0
    #: FIFO reads answered after the timeout, their scans kept (Modbus; docs/daq.md)
    late_answers: int = 0
    #: of ``missed``, the scans another Modbus master took off the module's FIFO
    foreign_taken: int = 0
    #: UTC ns of the first scan taken in the episode under way, or None (docs/daq.md)
    foreign_since_ns: int | None = None
    connected: bool = False
    last_error: str = ""
    #: monotonic start times of the latest reads, s (for the read-period jitter)
    read_starts: collections.deque = field(default_factory=lambda: collections.deque(maxlen=4096))

    @property
    def foreign_active(self) -> bool:
        """Whether another Modbus master is taking scans off the FIFO (an episode is on)."""
        return self.foreign_since_ns is not None
