"""A long soak of the real ``loopcal daemon`` against the emulated LDQ-412, with faults.

The module scans at 200 Hz (ten times the default: its 256-scan FIFO holds 1.28 s), with
the datasheet's answer times, scan 0 1809 µs after each power-on and a clock 200 ppm fast.
For as long as asked (default 30 min) faults come one at a time, at random (15 to 45 s
apart, seeded): the module power-cycled (off 0.3 to 2 s), gone from the network for 1 to
20 s, the daemon SIGSTOPped for up to 10 s, SIGKILLed and started again (in the first 60 %
of the run, so that one daemon lives long enough to watch its memory), SIGHUP reloads, the
recording's file system full for 5 to 30 s (a tmpfs filled up), bursts of slow answers.

At the end, against the module's own list of the scans it made:

- every recorded scan is one the module made, bit for bit, and none is recorded twice;
- every scan not recorded is explained: beyond the FIFO's reach when the daemon could read
  again, the daemon having read again soon after the fault that kept it away ended (a gap
  event says so: a SIGSTOP, the module gone, a SIGKILL), read by a daemon SIGKILLed before
  it could write it (the restarted daemon's gap event), lost with the module's power (a
  restart event), or lost with a FIFO answer that never arrived (a disconnect event);
  anything else fails the soak;
- every recorded scan with missed scans before it has its gap or restart event;
- RSS and open file descriptors of the longest-lived daemon did not grow;
- the daemon is still recording, and exits 0 on SIGTERM.

Run as root (to mount the tmpfs): ``python -m bench.soak [--minutes 30] [--seed 1]``.
Prints the fault counts and the figures; exits 1 if a check fails.
"""

from __future__ import annotations

import argparse
import collections
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from loopcal.daemon.recording import read_recordings
from loopcal.simulator.clock import RealClock
from loopcal.simulator.open_points import Latency, OpenPoints
from tests.support.emulator import hand_emulator

RATE = 200
PHASE_US = 1809
PPM = 200.0
FIFO_REACH_S = 256 / RATE
READ_PERIOD_S = 0.2
FLUSH_S = 1.0
KINDS = ("power", "gone", "sigstop", "sigkill", "sighup", "diskfull", "latency")
SLOW = Latency(min_ms=5.0, max_ms=10.0, slow_fraction=0.2, slow_ms=(50.0, 90.0))
#: how soon after a fault ends the daemon must read again (its backoff, at most a quarter of
#: the FIFO's reach at 200 Hz, a reconnect, a read period; a restarted daemon's start-up)
OUTAGE_SLACK_S = {"gone": 1.0, "sigstop": 0.6, "power": 1.0, "sigkill": 6.0}


@dataclass
class Fault:
    kind: str
    start: float  # monotonic s
    end: float = 0.0
    detail: str = ""


@dataclass
class Sample:
    t: float
    pid: int
    rss_kib: int
    fds: int


@dataclass
class Truth:
    """Every scan the module made: boot, counter, device time (µs), codes, host time."""

    boot: list[np.ndarray] = field(default_factory=list)
    counter: list[np.ndarray] = field(default_factory=list)
    t64: list[np.ndarray] = field(default_factory=list)
    codes: list[np.ndarray] = field(default_factory=list)

    def add(self, scans) -> None:
        if scans:
            self.boot.append(np.array([s.boot for s in scans]))
            self.counter.append(np.array([s.counter for s in scans], dtype=np.int64))
            self.t64.append(np.array([s.time_us for s in scans], dtype=np.int64))
            self.codes.append(np.array([s.codes for s in scans], dtype=np.int64))

    def arrays(self):
        return tuple(np.concatenate(x) for x in (self.boot, self.counter, self.t64, self.codes))


class Daemon:
    """``loopcal daemon --config PATH`` as a subprocess, its log lines kept."""

    def __init__(self, config: Path) -> None:
        self.config = config
        self.lines: list[tuple[float, str]] = []
        self.proc: subprocess.Popen | None = None
        self.started = 0

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "loopcal.daemon.cli", "daemon", "--config", str(self.config)],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        self.started += 1
        threading.Thread(target=self._read, args=(self.proc,), daemon=True).start()

    def _read(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def signal(self, sig: signal.Signals) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)


def sample(pid: int) -> Sample | None:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        rss = int(next(x for x in status.splitlines() if x.startswith("VmRSS:")).split()[1])
        return Sample(time.monotonic(), pid, rss, len(os.listdir(f"/proc/{pid}/fd")))
    except (OSError, StopIteration):
        return None


def fill(directory: Path) -> Path:
    """Fill the file system under ``directory`` up to its last few KiB."""
    st = os.statvfs(directory)
    free = st.f_bavail * st.f_frsize
    path = directory.parent / "filler"
    fd = os.open(path, os.O_CREAT | os.O_WRONLY, 0o600)
    try:
        os.posix_fallocate(fd, 0, max(free - (16 << 10), 1 << 10))
    except OSError:
        pass
    finally:
        os.close(fd)
    return path


class Soak:
    def __init__(self, args: argparse.Namespace, root: Path) -> None:
        self.args = args
        self.rng = random.Random(args.seed)
        self.root = root
        self.mnt = root / "fs"
        self.mnt.mkdir()
        self.mounted = False
        if os.geteuid() == 0 and not args.no_tmpfs:
            size = max(64, int(args.minutes * 60 * RATE * 400 / 2**20) + 64)
            r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}m", "tmpfs",
                                str(self.mnt)], capture_output=True)  # fmt: skip
            self.mounted = r.returncode == 0
        self.rec_dir = self.mnt / "rec"
        self.op = OpenPoints(scan_phase_us=PHASE_US, clock_ppm=PPM, latency=Latency())
        self.mono0 = time.monotonic_ns()
        self.clock = RealClock()
        self.emu = hand_emulator(rate=RATE, seed=args.seed, clock=self.clock,
                                 open_points=self.op)  # fmt: skip
        self.truth = Truth()
        self.boot_ns: dict[int, int] = {}
        self.faults: list[Fault] = []
        self.samples: list[Sample] = []
        self.config = root / "daemon.toml"
        self.daemon = Daemon(self.config)
        self.utc_minus_mono = time.time_ns() - time.monotonic_ns()

    # ------------------------------------------------------------------ running

    def take_truth(self) -> None:
        with self.emu.lock:
            dev = self.emu.device
            ns = dev.host_ns(dev.boot, 0)
            if ns is not None:
                self.boot_ns.setdefault(dev.boot, ns)
        self.truth.add(self.emu.take_truth())

    def run(self) -> None:
        self.emu.start()
        self.config.write_text(
            f'[daq]\nurl = "{self.emu.url}"\nread_period = {READ_PERIOD_S}\n\n'
            f'[recording]\ndirectory = "{self.rec_dir}"\nflush_period = {FLUSH_S}\n'
            f"rotate_seconds = 300\n",
            encoding="utf-8",
        )
        self.daemon.start()
        t_start = time.monotonic()
        t_faults_end = t_start + self.args.minutes * 60
        next_fault = t_start + self.rng.uniform(15, 30)
        current: Fault | None = None
        last_sample = 0.0
        while True:
            now = time.monotonic()
            self.take_truth()
            if now - last_sample >= 5.0 and self.daemon.proc is not None:
                last_sample = now
                s = sample(self.daemon.pid)
                if s is not None:
                    self.samples.append(s)
            if current is not None and now >= current.end:
                self.end_fault(current)
                current = None
                next_fault = now + self.rng.uniform(*self.args.gap)
            if current is None and now >= t_faults_end:
                break
            if current is None and now >= next_fault:
                current = self.start_fault(now, now - t_start < 0.6 * self.args.minutes * 60)
            time.sleep(0.25)
        time.sleep(5.0)  # a clean stretch: the daemon must be recording
        self.take_truth()
        self.rows_then = self.recorded_count()
        time.sleep(10.0)
        self.take_truth()
        self.last_rows_before_stop = self.recorded_count()
        t_stop = time.monotonic()
        self.daemon.signal(signal.SIGTERM)
        assert self.daemon.proc is not None
        self.exit_code = self.daemon.proc.wait(30)
        self.stop_s = time.monotonic() - t_stop
        time.sleep(0.2)
        self.take_truth()
        self.duration_s = time.monotonic() - t_start

    def recorded_count(self) -> int:
        try:
            return len(read_recordings(self.rec_dir))
        except Exception:  # noqa: BLE001 - a file being written: count later
            return -1

    def start_fault(self, now: float, kill_allowed: bool) -> Fault:
        kinds = [k for k in KINDS if k != "sigkill" or kill_allowed]
        if not self.mounted:
            kinds.remove("diskfull")
        kind = self.rng.choice(kinds)
        f = Fault(kind, now)
        if kind == "power":
            off = self.rng.uniform(0.3, 2.0)
            self.take_truth()
            self.emu.faults.restart(off)
            f.end, f.detail = now + off + 0.5, f"off {off:.2f} s"
        elif kind == "gone":
            d = self.rng.uniform(1, 20)
            self.emu.faults.disconnect()
            f.end, f.detail = now + d, f"{d:.1f} s"
        elif kind == "sigstop":
            d = self.rng.uniform(0.5, 10)
            self.daemon.signal(signal.SIGSTOP)
            f.end, f.detail = now + d, f"{d:.1f} s"
        elif kind == "sigkill":
            d = self.rng.uniform(0, 3)
            self.daemon.kill()
            f.end, f.detail = now + d, f"restarted after {d:.1f} s"
        elif kind == "sighup":
            self.daemon.signal(signal.SIGHUP)
            f.end = now + 1
        elif kind == "diskfull":
            d = self.rng.uniform(5, 30)
            self.filler = fill(self.rec_dir)
            f.end, f.detail = now + d, f"{d:.1f} s"
        elif kind == "latency":
            d = self.rng.uniform(5, 20)
            self.emu.faults.latency(SLOW)
            f.end, f.detail = now + d, f"{d:.1f} s"
        self.faults.append(f)
        print(f"{now - self.mono0 / 1e9:8.1f} s  {kind} {f.detail}", flush=True)
        return f

    def end_fault(self, f: Fault) -> None:
        if f.kind == "gone":
            self.emu.faults.reconnect()
        elif f.kind == "sigstop":
            self.daemon.signal(signal.SIGCONT)
        elif f.kind == "sigkill":
            self.daemon.start()
        elif f.kind == "diskfull":
            self.filler.unlink()
        elif f.kind == "latency":
            self.emu.faults.latency(self.op.latency)
        f.end = time.monotonic()

    def close(self) -> None:
        self.daemon.kill()
        self.emu.close()
        if self.mounted:
            subprocess.run(["umount", "-l", str(self.mnt)], check=False)

    # ------------------------------------------------------------------ checks

    def host_s(self, boot: np.ndarray, t64: np.ndarray) -> np.ndarray:
        """Monotonic host time at which each scan was taken."""
        base = np.array([self.boot_ns.get(int(b), 0) for b in boot], dtype=np.float64)
        return (self.mono0 + base + t64 * 1000.0 / (1 + PPM * 1e-6)) / 1e9

    def outage(self, t: float, read_again: float) -> str | None:
        """The fault that kept the daemon from reading a scan made at ``t`` until
        ``read_again``: one that began before ``t`` and ended at most its slack before the
        daemon read again (a SIGKILLed daemon's slack is its successor's start-up; None:
        none did, the daemon was late by itself)."""
        for f in self.faults:
            slack = OUTAGE_SLACK_S.get(f.kind)
            if slack is not None and f.start - 0.5 <= t <= read_again <= f.end + slack:
                return {"gone": "the module gone", "sigstop": "a SIGSTOP",
                        "sigkill": "a SIGKILL", "power": "a power cycle"}[f.kind]  # fmt: skip
        return None

    def check(self) -> bool:
        ok = True
        boot, counter, t64, codes = self.truth.arrays()
        produced = self.host_s(boot, t64)
        rec = read_recordings(self.rec_dir)
        rows = rec.scans
        pairs = zip(boot.tolist(), counter.tolist(), strict=True)
        key_truth = {(b, c): i for i, (b, c) in enumerate(pairs)}
        by_counter_codes = collections.defaultdict(list)
        for (b, c), i in key_truth.items():
            by_counter_codes[(c, tuple(codes[i]))].append(b)
        # which boot each recorded epoch is
        epoch_boot: dict[int, int] = {}
        for e in np.unique(rows["epoch"]):
            first = rows[rows["epoch"] == e][0]
            key = (int(first["counter64"]), tuple(int(x) for x in first["codes"]))
            cands = by_counter_codes[key]
            if len(cands) != 1:
                print(f"FAIL: recorded epoch {e} matches boots {cands}")
                return False
            epoch_boot[int(e)] = cands[0]
        rb = np.array([epoch_boot[int(e)] for e in rows["epoch"]])
        keys = list(zip(rb.tolist(), rows["counter64"].astype(np.int64).tolist(), strict=True))
        dup = len(keys) - len(set(keys))
        wrong = 0
        for (b, c), r in zip(keys, rows, strict=True):
            i = key_truth.get((b, c))
            if (
                i is None
                or t64[i] != int(r["time64_us"])
                or tuple(codes[i]) != tuple(int(x) for x in r["codes"])
            ):
                wrong += 1
        print(f"recorded {len(rows):,} scans in {len(rec.files)} files; "
              f"{wrong} not the module's, {dup} recorded twice")  # fmt: skip
        ok &= wrong == 0 and dup == 0
        # every missed count has its event
        events = rec.events
        ev_at = {(int(e.details.get("epoch", -1)), int(e.details.get("counter64", -1)))
                 for e in events if e.kind in ("gap", "restart")}  # fmt: skip
        unreported = [
            (int(r["epoch"]), int(r["counter64"]))
            for r in rows[rows["missed"] > 0]
            if (int(r["epoch"]), int(r["counter64"])) not in ev_at
        ]
        print(f"scans with missed scans before them: {(rows['missed'] > 0).sum()}, "
              f"without their gap or restart event: {len(unreported)}")  # fmt: skip
        ok &= not unreported
        # the scans not recorded, explained
        recorded = set(keys)
        first_boot = rb[0]
        first_rec = int(rows["counter64"][0])
        last_boot, last_c = rb[-1], int(rows["counter64"][-1])
        host_rec = (rows["host_ns"].astype(np.int64) - self.utc_minus_mono) / 1e9
        next_read: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for b in np.unique(rb):
            sel = rb == b
            next_read[int(b)] = (rows["counter64"][sel].astype(np.int64), host_rec[sel])
        kills = [f.start for f in self.faults if f.kind == "sigkill"]
        downs = [t for t, line in self.daemon.lines if "disconnect:" in line]
        why: collections.Counter = collections.Counter()
        tails: dict[int, int] = collections.Counter()
        unexplained = []
        for (b, c), i in key_truth.items():
            if (b, c) in recorded:
                continue
            if b < first_boot or (b == first_boot and c < first_rec):
                why["before the daemon's first read"] += 1
                continue
            if b > last_boot or (b == last_boot and c > last_c):
                why["after its last read (the end)"] += 1
                continue
            t = produced[i]
            cs, hs = next_read.get(b, (np.zeros(0, np.int64), np.zeros(0)))
            j = np.searchsorted(cs, c)
            if j == len(cs):
                why["lost with the module's power (restart event)"] += 1
                tails[b] += 1
                continue
            read_again = hs[j]
            if any(k - FLUSH_S - READ_PERIOD_S - 1.0 <= t <= k + 0.01 for k in kills):
                why["read by a SIGKILLed daemon, not yet written (gap event)"] += 1
            elif read_again - t > FIFO_REACH_S - 0.05:
                # beyond reach, and the daemon read again soon enough after the fault ended
                cause = self.outage(t, read_again)
                if cause is None:
                    unexplained.append((b, c, "read again too late", round(read_again - t, 3)))
                else:
                    why[f"beyond the FIFO's reach after {cause} (gap event)"] += 1
            elif any(t - 1.0 <= d <= read_again for d in downs):
                why["with a FIFO answer lost (disconnect event)"] += 1
            else:
                unexplained.append((b, c, "within reach", round(read_again - t, 3)))
        if self.args.verbose:
            for r, b, h in zip(rows, rb, host_rec, strict=True):
                if r["missed"]:
                    t = h - self.mono0 / 1e9
                    near = [f"{f.kind}@{f.start - self.mono0 / 1e9:.1f}" for f in self.faults
                            if f.start - 5 <= h <= f.end + 25]  # fmt: skip
                    print(
                        f"  gap at {t:7.1f} s: boot {b} counter {int(r['counter64'])} missed "
                        f"{int(r['missed'])} restarted {bool(r['restarted'])} {near}"
                    )
        made = len(key_truth)
        print(f"the module made {made:,} scans; not recorded:")
        for k, n in why.most_common():
            print(f"    {n:9,}  {k}")
        print(f"    {len(unexplained):9,}  unexplained {unexplained[:10]}")
        if tails:
            print(f"    (lost with the power, per power cycle: max {max(tails.values())}, "
                  f"median {int(np.median(list(tails.values())))})")  # fmt: skip
        ok &= not unexplained
        # resources
        per_pid = collections.defaultdict(list)
        for s in self.samples:
            per_pid[s.pid].append(s)
        longest = max(per_pid.values(), key=lambda v: v[-1].t - v[0].t)
        warm = [s for s in longest if s.t - longest[0].t >= 60]
        if len(warm) >= 4:
            q = max(1, len(warm) // 5)
            rss0 = np.median([s.rss_kib for s in warm[:q]]) / 1024
            rss1 = np.median([s.rss_kib for s in warm[-q:]]) / 1024
            fd0, fd1 = warm[0].fds, warm[-1].fds
            span = (warm[-1].t - warm[0].t) / 60
            rss_max = max(s.rss_kib for s in warm) / 1024
            print(f"longest-lived daemon (pid {longest[0].pid}, {span:.1f} min after its first "
                  f"minute): RSS {rss0:.1f} -> {rss1:.1f} MiB (max {rss_max:.1f}), "
                  f"open fds {fd0} -> {fd1} (max {max(s.fds for s in warm)})")  # fmt: skip
            ok &= rss1 - rss0 < 8.0 and fd1 <= fd0 + 2
        else:
            print("FAIL: no daemon lived long enough to watch its memory")
            ok = False
        # still recording
        last_host = float(host_rec[-1])
        grew = self.last_rows_before_stop - self.rows_then
        print(f"still recording at the end: {grew:,} scans written in the last 10 s before "
              f"SIGTERM ({10 * RATE:,} made); exit status {self.exit_code} after "
              f"{self.stop_s:.2f} s")  # fmt: skip
        ok &= self.exit_code == 0 and grew >= 9 * RATE and last_host > 0
        return bool(ok)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30.0, help="how long faults come (30)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--gap", type=float, nargs=2, default=(15.0, 45.0), metavar=("MIN", "MAX"),
                    help="seconds between one fault's end and the next (15 45)")  # fmt: skip
    ap.add_argument("--keep", type=Path, default=None, help="copy the recordings here")
    ap.add_argument("--no-tmpfs", action="store_true", help="no file-system-full faults")
    ap.add_argument("-v", "--verbose", action="store_true", help="list every gap")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="loopcal-soak-"))
    soak = Soak(args, root)
    try:
        print(f"soak: {args.minutes:g} min of faults, loopcal daemon against the emulated "
              f"LDQ-412 over Modbus TCP at {RATE} Hz (FIFO reach {FIFO_REACH_S:.2f} s), seed "
              f"{args.seed}; recordings on {'a tmpfs' if soak.mounted else 'disk'}",
              flush=True)  # fmt: skip
        soak.run()
        counts = collections.Counter(f.kind for f in soak.faults)
        print(f"\nfaults injected in {soak.duration_s / 60:.1f} min: "
              + ", ".join(f"{k} {counts.get(k, 0)}" for k in KINDS)
              + f"; daemon started {soak.daemon.started} times")  # fmt: skip
        ok = soak.check()
        if args.keep:
            shutil.copytree(soak.rec_dir, args.keep, dirs_exist_ok=True)
        print("soak: PASS" if ok else "soak: FAIL")
        return 0 if ok else 1
    finally:
        soak.close()
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
