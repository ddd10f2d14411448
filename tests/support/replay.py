"""A recording replayed (``loopcal replay``, or its Player in this process) and recorded
again (``loopcal record``), and the comparison a round trip must pass. The recordings it
replays: :func:`tests.support.rows.synthetic_rows` written with
:func:`tests.support.recordings.write_directory`."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np

from .drivers import tcp_line
from .processes import Proc, listening_url, record


def replay_and_record(
    src: Path, out: Path, transport: str, speed: float, *options: str
) -> tuple[Proc, Proc]:
    """``loopcal replay SRC [options]`` and ``loopcal record`` reading it (both running); a
    serial transport behind the replay's device server (``--line tcp``: the replay runs on
    a real clock, tests.support.drivers.tcp_line).

    The recorder waits 3 s for an answer (the datasheet's 0.1 s, and 2.5 s for a FIFO
    read, by default): a loaded machine has held a pseudo-terminal's bytes back for 2.7 s
    (tests/support/drivers.py), and a FIFO answer given up on takes its scans with it."""
    line = [f"--{k}={v}" for k, v in tcp_line(transport).items()]  # --line=tcp
    player = Proc(["replay", str(src), "--transport", transport, "--speed", f"{speed:g}",
                   *line, *options])  # fmt: skip
    return player, record(
        listening_url(player, timeout=30), out, "--read-period", "0.05", "--timeout", "3"
    )


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
    player = PlayerThread(rows, transport, rate, speed, **{**tcp_line(transport), **kw})
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


def assert_same_scans(original: np.ndarray, again: np.ndarray, *, polled: bool = False) -> None:
    """A recording of a replay holds exactly the original scans: counters, device times,
    codes, epochs (up to where the count starts), missed counts, restarts, rail bits, and
    the measured status's rail and fault bits.

    ``polled``: recorded by polling (ASCII), where a poll the host's scheduler delays past
    the next scan misses one. How many depends on the machine's load, not on loopcal (a
    quiet machine misses none or one of 220; a 2-core CI runner shared by four test
    workers and two CPU hogs 41 of 91), so no count is bounded here: each must be
    declared (the next scan recorded counts it in its ``missed``), every scan recorded is
    still the original's, bit for bit, and every power-on is in the recording (the
    replay holds each power-on's first and last scan until a client read it). The polls'
    own quality is measured where the load is not the machine's:
    ``python -m bench.bench_stamps``."""
    if polled:
        e0, e1 = int(original["epoch"][0]), int(again["epoch"][0]) if len(again) else 0
        have = set(zip((again["epoch"].astype(np.int64) - e1).tolist(),
                       again["counter64"].tolist(), strict=True))  # fmt: skip
        keys = zip((original["epoch"].astype(np.int64) - e0).tolist(),
                   original["counter64"].tolist(), strict=True)  # fmt: skip
        present = np.array([k in have for k in keys], dtype=bool)
        epochs = original["epoch"]
        assert set(epochs[present].tolist()) == set(epochs.tolist()), (
            f"a power-on is missing: {int((~present).sum())} of {len(original)} scans missed"
        )
        idx = np.flatnonzero(present)
        # a scan recorded counts the original scans absent just before it, and what each
        # of those counted itself (a gap the original had there)
        absent_count = np.cumsum(np.where(present, 0, original["missed"].astype(np.int64) + 1))
        before = np.diff(np.r_[0, absent_count[idx]])
        same_epoch = np.r_[False, original["epoch"][idx][1:] == original["epoch"][idx][:-1]]
        sub = original[idx].copy()
        sub["missed"] += np.where(same_epoch, before, 0).astype(sub["missed"].dtype)
        if len(idx) and idx[0]:  # missed before the first scan recorded: not its count
            sub["missed"][0] = again["missed"][0]
        original = sub
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
