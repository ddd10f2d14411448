"""Recordings that test a replay: scans with a phase, a device clock running fast or
slow, 32-bit counter and time wraps, missed scans and restarts in the middle, written with
the project's own recording writer; and the comparison a round trip must pass."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
from fuzz_helpers import T0, write_rows
from recorder_helpers import Proc, listening_url, record

from loopcal.daemon import recording as rec
from loopcal.daemon import scans as S
from loopcal.daemon.recording import read_recordings

U32 = 1 << 32


def _power_on(first: int, n: int, *, phase_us: int, rate: int, gaps: dict[int, int], seed: int):
    """Counters first.. (n scans, with ``gaps``: index -> scans skipped before it), device
    times ``phase + counter * period`` (the module's own µs), random but smooth codes."""
    skip = np.zeros(n, dtype=np.int64)
    for i, k in gaps.items():
        skip[i] = k
    counter = first + np.arange(n, dtype=np.int64) + np.cumsum(skip)
    time_us = phase_us + counter * (1_000_000 // rate)
    rng = np.random.default_rng(seed)
    codes = np.clip(2048 + np.cumsum(rng.integers(-40, 41, (n, 4)), axis=0), 1, 4094)
    return counter, time_us, codes, skip


def synthetic_rows(rate: int = 50) -> np.ndarray:
    """Three power-ons of an independent module, as a recorder would have recorded them:

    0. on for 71.6 min when the recording starts: the device time passes 2**32 µs in
       the middle; 1 scan missed; channel 2 at the rail for a while;
    1. a restart: scan 0 came 700 µs after power-on; 3 scans missed; the clock runs 200
       ppm slow (the host stamps drift); a sensor fault;
    2. a restart the recorder saw late (6.8 years of scans at 20 Hz never read): the
       counter passes 2**32 and the device time wraps; scan 0 came 1809 µs after
       power-on; 5 scans missed; the clock 200 ppm fast.

    Each restart's 32-bit counter goes back, as the ASCII protocol needs to see one (it
    cannot clear the restart flag).
    """
    period = 1_000_000 // rate
    parts = [
        (_power_on(U32 // period - 40, 80, phase_us=0, rate=rate, gaps={50: 1}, seed=3), 0.0),
        (_power_on(0, 60, phase_us=700, rate=rate, gaps={25: 3}, seed=2), -200e-6),
        (_power_on(U32 - 40, 80, phase_us=1809, rate=rate, gaps={30: 5}, seed=1), 200e-6),
    ]
    out, host0 = [], T0
    for epoch, ((counter, time_us, codes, skip), ppm) in enumerate(parts):
        rows = S.empty(len(counter))
        rows["counter64"] = counter
        rows["time64_us"] = time_us
        rows["epoch"] = epoch + 3  # a recorder that had seen restarts before
        rows["codes"] = codes
        rows["missed"] = skip
        rows["restarted"][0] = True
        if epoch:
            rows["missed"][0] = counter[0]
        elapsed = (time_us - time_us[0]) * 1000 / (1 + ppm)  # the host's ns
        rows["stamp_ns"] = host0 + elapsed.astype(np.int64) + time_us[0] * 1000
        rows["host_ns"] = rows["stamp_ns"] + 3_000_000
        rows["from_fifo"] = True
        out.append(rows)
        host0 = int(rows["stamp_ns"][-1]) + 500_000_000  # off for half a second
    rows = np.concatenate(out)
    rows["codes"][20:30, 1] = 4095  # channel 2 at the rail
    rows["codes"][100:106, 2] = 4095  # channel 3 sensor fault
    rows["status"] = 1 << 9  # the restart flag, as an ASCII recorder never clears it
    rail = (rows["codes"] == 0) | (rows["codes"] == 4095)
    rows["status"] |= (rail * (1 << np.arange(4))).sum(axis=1).astype(np.uint16)
    rows["status"][100:106] |= 1 << 6
    rows["time_measured"] = rows["status_measured"] = True
    return rows


def write_recording(directory: Path, rows: np.ndarray, rate: int) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    meta = rec.metadata_records(
        device={"model": "LDQ412", "scan_rate_hz": str(rate)}, controller={}, command="tests"
    )
    write_rows(directory / rec.recording_name(int(rows["stamp_ns"][0])), rows, per=25,
               metadata=meta, fsync=False)  # fmt: skip
    return directory


def replay_and_record(
    src: Path, out: Path, transport: str, speed: float, *options: str
) -> tuple[Proc, Proc]:
    """``loopcal replay SRC [options]`` and ``loopcal record`` reading it (both running)."""
    player = Proc(["replay", str(src), "--transport", transport, "--speed", f"{speed:g}",
                   *options])  # fmt: skip
    return player, record(listening_url(player, timeout=30), out, "--read-period", "0.05")


class PlayerThread:
    """A :class:`loopcal.simulator.replay.Player` in this process (for settings the command has no
    options for), run in a thread like ``loopcal replay``: ``lines`` and ``wait`` as a
    :class:`Proc` has them, for :func:`finish`."""

    def __init__(self, rows: np.ndarray, transport: str, rate: int, speed: float, **kw) -> None:
        from loopcal.daemon.commands.replay import power_ons
        from loopcal.simulator.replay import Player

        self.player = Player(power_ons(rows), transport=transport, rate_hz=rate, speed=speed,
                             **kw).start()  # fmt: skip
        self.stop = threading.Event()
        self.done = threading.Event()
        self.text = ""
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        self.player.run(self.stop, wait_for_client=True)
        self.done.set()

    def wait_for(self, pattern: str, timeout: float) -> int:
        assert pattern == "replay finished" and self.done.wait(timeout), "replay did not end"
        return 0

    def wait(self) -> int:
        self._thread.join(10)
        self.player.close()
        return 0


def replay_in_process(
    rows: np.ndarray, out: Path, transport: str, rate: int, speed: float, **kw
) -> tuple[PlayerThread, Proc]:
    player = PlayerThread(rows, transport, rate, speed, **kw)
    # a 0.5 s timeout: the module here shares this process, and its slow answers (50-70 ms
    # on purpose) can reach the recorder after 100 ms on a loaded machine, and a FIFO
    # answer that times out takes its scans with it
    return player, record(player.player.url, out, "--read-period", "0.05", "--timeout", "0.5")


def finish(player: Proc | PlayerThread, recorder: Proc, *, settle_s: float = 0.0) -> None:
    """Wait for the replay's end (and ``settle_s`` more, for the recorder's last reads after
    a short tail), then stop the recorder: both must exit 0."""
    player.wait_for("replay finished", timeout=120)
    time.sleep(settle_s)
    rc_rec, _ = recorder.stop()
    assert rc_rec == 0 and player.wait() == 0, recorder.text + "\n" + player.text


def assert_same_scans(original: np.ndarray, again: np.ndarray) -> None:
    """A recording of a replay holds exactly the original scans: counters, device times,
    codes, epochs (up to where the count starts), missed counts, restarts, rail bits, and
    the measured status's rail and fault bits."""
    key = [(int(r["counter64"]), int(r["time64_us"])) for r in again]
    want = [(int(r["counter64"]), int(r["time64_us"])) for r in original]
    assert key == want, _first_difference(want, key)
    for name in ("codes", "missed", "restarted"):
        np.testing.assert_array_equal(again[name], original[name], err_msg=name)
    np.testing.assert_array_equal(
        again["epoch"] - again["epoch"][0], original["epoch"] - original["epoch"][0]
    )
    np.testing.assert_array_equal(again["status"] & 0x0F, original["status"] & 0x0F)
    both = again["status_measured"] & original["status_measured"]
    np.testing.assert_array_equal(again["status"][both] & 0xFF, original["status"][both] & 0xFF)


def _first_difference(want: list, got: list) -> str:
    for i, (a, b) in enumerate(zip(want, got, strict=False)):
        if a != b:
            return f"scan {i}: recorded {a}, replayed {b} ({len(want)} vs {len(got)} scans)"
    return f"{len(want)} scans recorded, {len(got)} replayed"


def read_scans(directory: Path) -> np.ndarray:
    return read_recordings(directory).scans
