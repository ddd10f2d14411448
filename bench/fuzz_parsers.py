"""A long fuzz run of every parser of outside input, printing counts per outcome.

    python -m bench.fuzz_parsers [--cases 3000] [--seed 1] [--only recording|ascii|url|toml]

For each parser, random inputs near valid ones (and plain random bytes) go in, and each
outcome is counted:

- recordings (``read_recordings`` on a real recording damaged by bit flips, truncations,
  zero runs, zero tails, duplicated and swapped chunks, bad length fields, overwrites; a
  closed and an unclosed file): ``intact``, ``reported`` (scans lost or dropped, and the
  file's warning or note says so), ``declared`` (RecordingError), and the failures
  ``silent loss``, ``duplicated``, ``fabricated``, ``undeclared: <exception>``, ``hang``;
- the ASCII answer parser: ``parsed`` or ``protocol error``; the driver URL parser:
  ``accepted`` or ``ValueError``; the two TOML loaders: ``loaded`` or their own error;
  anything else is ``undeclared``.

The last lines say how many failures there were (the target: 0). A case taking more than
10 s counts as a hang.
"""

from __future__ import annotations

import argparse
import collections
import random
import signal
import string
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from loopcal.daemon.config.controller import (
    ControllerConfigError,
    load_controller_config,
    render_initial_config,
)
from loopcal.daemon.recorder.settings import SettingsError, load_daemon_config
from loopcal.daemon.recording import recording_name
from loopcal.drivers import DAQInvalidCommand, DAQProtocolError, driver_for_url
from loopcal.drivers import ascii as ascii_proto
from loopcal.drivers.ldq412 import ascii_checksum
from tests.support.mutations import (
    ACCEPTABLE,
    ASCII_ANSWERS,
    DAEMON_TOML,
    MUTATIONS,
    closed_and_unclosed,
    judge,
)
from tests.support.rows import T0, make_rows

HANG_S = 10


class Hang(Exception):
    pass


def _alarm(*_: object) -> None:
    raise Hang()


def run_case(fn: Callable[[], str]) -> str:
    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(HANG_S)
    try:
        return fn()
    except Hang:
        return "hang"
    except Exception as exc:  # noqa: BLE001 - what the count is about
        return f"undeclared: {type(exc).__name__}"
    finally:
        signal.alarm(0)


# ---------------------------------------------------------------------------- recordings


def _draw(rnd: random.Random, kind: str, size: int) -> list:
    """Random arguments for a mutation of a file of ``size`` bytes."""
    if kind == "flip":
        return [[rnd.randrange(size * 8) for _ in range(rnd.randint(1, 8))]]
    if kind == "truncate":
        return [rnd.randrange(size)]
    if kind in ("zero_run", "zero_tail"):
        return [rnd.randrange(size), rnd.randint(1, 8192 if kind == "zero_run" else 16384)]
    if kind in ("dup_chunk", "swap_chunks"):
        return [rnd.randrange(1 << 20)]
    if kind == "bad_length":
        value = rnd.choice([rnd.randrange(1 << 64), rnd.randrange(256), rnd.randrange(1 << 24)])
        return [rnd.randrange(1 << 20), value]
    return [rnd.randrange(size), rnd.randbytes(rnd.randint(1, 64))]


def recording_cases(rnd: random.Random, n: int, work: Path) -> collections.Counter:
    rows = make_rows(2628)
    data = closed_and_unclosed(rows, work)
    target = work / recording_name(T0)
    counts: collections.Counter = collections.Counter()
    for _ in range(n):
        closed = rnd.random() < 0.5
        d = data[closed]
        kind = rnd.choice(list(MUTATIONS))
        args = _draw(rnd, kind, len(d))
        target.write_bytes(MUTATIONS[kind](d, *args))
        verdict = run_case(lambda: judge(rows, target))
        counts[(kind, verdict.split(":")[0] if verdict.startswith("undeclared") else verdict)] += 1
        if verdict not in ACCEPTABLE:
            print(f"  FAILURE {kind} {args!r:.80} -> {verdict}", flush=True)
    return counts


# ---------------------------------------------------------------------------- wire and text


def _near(rnd: random.Random, good: bytes) -> bytes:
    if rnd.random() < 0.2:
        return rnd.randbytes(rnd.randint(0, 48))
    out = bytearray(good)
    for _ in range(rnd.randint(1, 3)):
        op = rnd.randrange(3)
        i = rnd.randrange(len(out) + 1)
        if op == 0 and out:
            out[min(i, len(out) - 1)] = rnd.randrange(256)
        elif op == 1:
            out[i:i] = rnd.randbytes(rnd.randint(1, 3))
        else:
            del out[i : i + rnd.randint(1, 3)]
    return bytes(out)


def ascii_case(rnd: random.Random) -> str:
    checksum = rnd.random() < 0.5
    good = rnd.choice(ASCII_ANSWERS)
    if checksum:  # the same answer as a module in checksum mode sends it
        good = good[:-1] + ascii_checksum(good[:-1]) + good[-1:]
    line = _near(rnd, good) if rnd.random() < 0.9 else good
    addr = rnd.randrange(256) if rnd.random() < 0.2 else 1
    try:
        body = ascii_proto.unframe(line, checksum=checksum)
        payload = ascii_proto.parse_ack(body, addr) if body[:1] == b"!" else None
        if payload is not None:
            (ascii_proto.parse_firmware if b"." in payload else ascii_proto.parse_rate)(payload)
        elif len(body) == 4:
            ascii_proto.parse_channel(body, addr)
        else:
            ascii_proto.parse_scan(body, addr)
    except (DAQProtocolError, DAQInvalidCommand):
        return "protocol error"
    return "parsed"


URLS = ["modbus-tcp://192.168.1.50:502?unit=1&fifo=1", "modbus-rtu:///dev/ttyUSB0?baud=115200&"
        "unit=1&parity=N&stopbits=1", "ascii:///dev/ttyUSB0?baud=115200&addr=01&checksum=1",
        "ascii://COM3?addr=1F"]  # fmt: skip


def url_case(rnd: random.Random) -> str:
    raw = _near(rnd, rnd.choice(URLS).encode())
    url = raw.decode("latin-1") if rnd.random() < 0.5 else raw.decode("utf-8", "replace")
    try:
        driver_for_url(url)
    except ValueError:
        return "ValueError"
    return "accepted"


def _text_near(rnd: random.Random, base: str) -> bytes:
    lines = base.splitlines()
    r = rnd.random()
    if r < 0.4:
        i = rnd.randrange(len(lines))
        junk = "".join(rnd.choice(string.printable) for _ in range(rnd.randint(0, 30)))
        key = lines[i].split("=")[0] if "=" in lines[i] else ""
        lines[i] = f"{key}= {junk}" if key and rnd.random() < 0.7 else junk
        return "\n".join(lines).encode()
    if r < 0.8:
        return _near(rnd, base.encode())
    return rnd.randbytes(rnd.randint(0, 300))


def toml_case(rnd: random.Random, work: Path, daemon_text: str) -> str:
    path = work / "cfg.toml"
    if rnd.random() < 0.5:
        path.write_bytes(_text_near(rnd, render_initial_config()))
        try:
            load_controller_config(path)
        except ControllerConfigError:
            return "controller: refused"
        return "controller: loaded"
    path.write_bytes(_text_near(rnd, daemon_text))
    try:
        load_daemon_config(path)
    except SettingsError:
        return "daemon: refused"
    return "daemon: loaded"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", type=int, default=3000, help="cases per parser (3000)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", choices=("recording", "ascii", "url", "toml"), default=None)
    args = ap.parse_args()
    rnd = random.Random(args.seed)
    failures = 0
    good = ACCEPTABLE | {"parsed", "protocol error", "accepted", "ValueError",
                        "controller: refused", "controller: loaded", "daemon: refused",
                        "daemon: loaded"}  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        parts: dict[str, Callable[[], collections.Counter]] = {
            "recording": lambda: recording_cases(rnd, args.cases, work),
            "ascii": lambda: collections.Counter(
                run_case(lambda: ascii_case(rnd)) for _ in range(args.cases)),
            "url": lambda: collections.Counter(
                run_case(lambda: url_case(rnd)) for _ in range(args.cases)),
            "toml": lambda: collections.Counter(
                run_case(lambda: toml_case(rnd, work, DAEMON_TOML)) for _ in range(args.cases)),
        }  # fmt: skip
        for name, fn in parts.items():
            if args.only and name != args.only:
                continue
            t0 = time.perf_counter()
            counts = fn()
            took = time.perf_counter() - t0
            total = sum(counts.values())
            print(f"{name}: {total} cases in {took:.1f} s")
            for key, n in sorted(counts.items(), key=lambda kv: str(kv[0])):
                outcome = key[1] if isinstance(key, tuple) else key
                flag = "" if outcome in good else "   <-- FAILURE"
                failures += 0 if outcome in good else n
                print(f"  {' / '.join(key) if isinstance(key, tuple) else key}: {n}{flag}")
    print(f"failures (undeclared exceptions, hangs, silent losses, duplicates, "
          f"fabricated scans): {failures}")  # fmt: skip
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
