"""Technician sessions for the worker tests, written straight from the simulator's offline
scans (what an emulated module makes, without waiting for it)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from loopcal.calibration.parameters import PAPER7
from loopcal.calibration.simulate import perturbed_truth
from loopcal.daemon import recording as rec
from loopcal.simulator.offline import mechanism_scans
from loopcal.simulator.scenarios import GuidedHand, HandMoves, Scenario

from .recordings import write_directory
from .rows import T0, rows_from

#: a technician pausing about a second between moves
PAUSE_S = (0.8, 1.5)


@dataclass
class Session:
    directory: Path
    truth: np.ndarray
    seed: int


def calibrated_config(path: Path, params: np.ndarray, std: float = 0.01) -> Path:
    """A controller config at ``path`` with ``params``, as loopcal's calibration leaves it:
    ``[provenance]`` with ``std`` mm on each offset (the previous version not kept)."""
    from loopcal.daemon.config.controller import load_controller_config, write_initial_config
    from loopcal.daemon.worker.writeback import write_back

    write_initial_config(path, params=params)
    stds = dict.fromkeys(("d01", "d02", "d03", "d04"), std)
    provenance = {"method": "ml", "written_utc": "2026-12-01T08:00:00Z", "std": stds}
    write_back(load_controller_config(path), np.asarray(params, dtype=float), provenance)
    for prev in path.parent.glob(f"{path.name}.*.prev"):
        prev.unlink()
    return path


def truth_for(seed: int) -> np.ndarray:
    """A shoulder joint whose LVDTs were refitted (offsets up to 3 mm off) and whose
    geometry differs from the blueprint by up to 0.5 mm."""
    return perturbed_truth(np.random.default_rng([seed, 7]), model=PAPER7)


def trim(src: Path, dst: Path, first: int, stop: int) -> Path:
    """Copy the scans with counters first..stop-1 of a recording into a new one (so that a
    test calibrates the same scans every run, whenever its recorder happened to start)."""
    scans = rec.read_recordings(src).scans
    keep = scans[(scans["counter64"] >= first) & (scans["counter64"] < stop)]
    assert len(keep) == stop - first, f"{src}: scans {first}..{stop - 1} not all recorded"
    return write_directory(dst, keep, command="trim")


def write_session(
    path: Path,
    scenario: Scenario,
    truth: np.ndarray,
    seconds: float,
    *,
    seed: int = 0,
    rate: int = 20,
    hours_per_file: float = 1.0,
    edit=None,
    drifts=(),
    t0: int = T0,
) -> int:
    """Write an offline-simulated session as recording files in ``path``; returns scans.

    edit: called with the codes (n, 4) to change them (a stuck sensor, say). drifts:
    :class:`loopcal.simulator.drift.OffsetDrift` of the sensors' offsets. t0: the first scan's
    stamp, ns since the Unix epoch."""
    n = round(seconds * rate)
    time_us, codes = mechanism_scans(scenario, truth, n, rate_hz=rate, noise_volts=0.04,
                                     seed=seed, drifts=drifts)  # fmt: skip
    if edit is not None:
        edit(codes)
    rows = rows_from(time_us, codes, t0=t0)
    write_directory(path, rows, rate=rate, scans_per_file=round(hours_per_file * 3600 * rate))
    return n


def hand_rows(n: int, *, seed: int = 1, first: int = 0, read_every: int = 4,
              twist_every: int = 0) -> np.ndarray:  # fmt: skip
    """``n`` scans of a technician's hand-moved session at 20 Hz (the motion of ``seed``),
    counters (and device times) from ``first`` on, as the recorder stamps them: the offline
    mechanism's codes (40 mV of noise), one host receive time per read of ``read_every``
    scans, 1 to 3 ms after the last one's stamp. twist_every: every so many moves twist the
    plate (:class:`~loopcal.simulator.scenarios.HandMoves`; 0: never)."""
    truth = truth_for(seed)
    motion = HandMoves(seed, params=truth, pause_s=PAUSE_S, twist_every=twist_every)
    time_us, codes = mechanism_scans(motion, truth, n, rate_hz=20, noise_volts=0.04, seed=seed)
    rows = rows_from(time_us + first * 50_000, codes, counter=np.arange(first, first + n))
    return _received(rows, np.random.default_rng([seed, 3]), read_every)


def _received(rows: np.ndarray, rng: np.random.Generator, read_every: int) -> np.ndarray:
    """``rows`` with the host's receive times: one per read of ``read_every`` scans, 1 to 3
    ms after the last one's stamp (``rng``); a last partial read 2 ms after each stamp."""
    n = len(rows)
    last = rows["stamp_ns"][read_every - 1 :: read_every]
    latency = rng.integers(1_000_000, 3_000_000, len(last))
    host = np.repeat(last + latency, read_every)[:n]
    rows["host_ns"][: len(host)] = host
    rows["host_ns"][len(host) :] = rows["stamp_ns"][len(host) :] + 2_000_000
    return rows


class _Later(Scenario):
    """``scenario`` from ``offset_s`` on: its time 0 is the other's ``offset_s``."""

    def __init__(self, scenario: Scenario, offset_s: float) -> None:
        self.scenario, self.offset_s = scenario, offset_s

    def rotation(self, t: np.ndarray) -> np.ndarray:
        return self.scenario.rotation(np.asarray(t, dtype=float) + self.offset_s)


class GuidedSession:
    """A technician following the live guidance, one second at a time: the closed loop,
    offline. Its scans are the offline emulator's (40 mV of noise, 20 Hz, as
    :func:`hand_rows`; each second's noise from ``[seed, 5, second]``) of a
    :class:`~loopcal.simulator.scenarios.GuidedHand` on the mechanism of ``seed``
    (:func:`truth_for`), steered between seconds by what the guidance said of the scans so
    far (:meth:`steer`). technician: GuidedHand's imprecision (``late``, ``wrong``, ...)."""

    RATE = 20

    def __init__(self, seed: int, *, read_every: int = 4, **technician) -> None:
        assert self.RATE % read_every == 0, "a second holds whole reads"
        self.seed, self.read_every = seed, read_every
        self.truth = truth_for(seed)
        self.motion = GuidedHand(seed, params=self.truth, pause_s=PAUSE_S, **technician)
        self._chunks: list[np.ndarray] = []

    @property
    def seconds(self) -> int:
        """The seconds recorded so far."""
        return len(self._chunks)

    @property
    def rows(self) -> np.ndarray:
        """Every scan so far, as the recorder stamps them."""
        return np.concatenate(self._chunks) if self._chunks else rows_from([], np.zeros((0, 4)))

    def advance(self) -> np.ndarray:
        """Record one more second; returns its scans."""
        k, n = self.seconds, self.RATE
        later = _Later(self.motion, float(k))
        time_us, codes = mechanism_scans(later, self.truth, n, rate_hz=n, noise_volts=0.04,
                                         seed=[self.seed, 5, k])  # fmt: skip
        rows = rows_from(time_us + k * 1_000_000, codes, counter=np.arange(k * n, (k + 1) * n))
        self._chunks.append(_received(rows, np.random.default_rng([self.seed, 3, k]),
                                      self.read_every))  # fmt: skip
        return self._chunks[-1]

    def follow(self, guidance, seconds: int) -> None:
        """The closed loop: record second by second, each second's scans fed to
        ``guidance`` (a :class:`loopcal.daemon.live.guidance.Guidance` judging at every
        feed, ``period_s=0``) and its advice (``"advice"`` of its JSON, as a client reads it)
        shown to the technician, until it is enough or ``seconds`` are recorded."""
        while self.seconds < seconds and not guidance.done:
            guidance.feed(self.advance())
            self.steer(guidance.last.as_json()["advice"])

    def steer(self, advice) -> None:
        """Show the technician ``advice`` (the guidance's ``"advice"`` JSON, or None) now:
        the moves that start from here on follow it."""
        self.motion.steer(advice, float(self.seconds))
