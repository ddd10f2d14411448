"""Compacting closed recordings: the same scans, events and messages in a few large chunks,
readable by every reader, verified before it replaces the original, never losing anything
when killed, never touching the file being written."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from mcap.reader import make_reader

from loopcal.daemon import recording as rec
from loopcal.daemon.recording.compact import compact
from tests.support.emulator import assert_matches_truth, hand_emulator
from tests.support.js import read_ts
from tests.support.mutations import chunk_spans, flip_bits, identities, tear_chunk
from tests.support.processes import LOOPCAL, loopcal, loopcal_main, record
from tests.support.recordings import write_recording
from tests.support.rows import T0, make_rows

pytestmark = pytest.mark.timeout(120)


def _recording(tmp_path, n=3000, close=True):
    path = tmp_path / rec.recording_name(T0)
    write_recording(path, make_rows(n), close=close)
    return path


@pytest.mark.slow
def test_a_compacted_file_holds_the_same_and_reads_everywhere(tmp_path, node_reader):
    path = _recording(tmp_path)
    before = rec.read_recordings(path)
    with open(path, "rb") as f:
        counts = make_reader(f).get_summary().statistics.channel_message_counts
    r = compact(path)
    assert r.done and r.chunks_before == 300 and r.chunks_after <= 6
    after = rec.read_recordings(path)
    assert identities(after.scans) == identities(before.scans)
    assert [e.to_json() for e in after.events] == [e.to_json() for e in before.events]
    assert after.files[0].complete and after.files[0].intact
    assert "compacted_utc" in after.files[0].metadata["loopcal"]
    assert {k: v for k, v in after.files[0].metadata["device"].items()} == \
        before.files[0].metadata["device"]  # fmt: skip
    assert after.files[0].metadata["loopcal"]["format"] == rec.COMPACT_FORMAT
    with open(path, "rb") as f:  # the mcap library: every message, every channel
        reader = make_reader(f)
        summary = reader.get_summary()
        scans_id = next(i for i, c in summary.channels.items() if c.topic == rec.TOPIC_SCANS)
        assert summary.schemas[summary.channels[scans_id].schema_id].name == \
            rec.SCAN_COLUMNS_SCHEMA  # fmt: skip
        got = summary.statistics.channel_message_counts
        # the same messages, but the scans' blocks: one block of columns a minute (150 s)
        assert {k: v for k, v in got.items() if k != scans_id} == \
            {k: v for k, v in counts.items() if k != scans_id}  # fmt: skip
        assert got[scans_id] == 3
        n = sum(1 for _ in reader.iter_messages(log_time_order=True))
    assert n == sum(got.values())
    ts = read_ts(node_reader, path)  # Foxglove's TypeScript reader: it must read it
    assert ts["packedScans"] == 3000 and ts["counts"]["/daq/scans"] == 3
    assert not compact(path).done  # already compact


@pytest.mark.slow
def test_files_not_closed_or_damaged_are_left_alone(tmp_path):
    (tmp_path / "open").mkdir()
    open_file = _recording(tmp_path / "open", close=False)
    data = open_file.read_bytes()
    assert not compact(open_file).done and open_file.read_bytes() == data
    damaged = _recording(tmp_path)
    raw = tear_chunk(damaged, 10)
    r = compact(damaged)
    assert not r.done and "damaged" in r.reason and damaged.read_bytes() == raw


@pytest.mark.slow
@pytest.mark.parametrize("step", ["compact-written", "compact-verified", "compact-renamed"])
def test_killed_while_compacting_loses_nothing(tmp_path, step):
    path = _recording(tmp_path)
    rows = rec.read_recordings(path).scans
    proc = loopcal("compact", path, env={"LOOPCAL_KILL_AT": step})
    assert proc.returncode == -signal.SIGKILL, proc.stdout + proc.stderr
    out = rec.read_recordings(path)
    assert identities(out.scans) == identities(rows) and out.files[0].intact
    compacted = "compacted_utc" in out.files[0].metadata["loopcal"]
    assert compacted == (step == "compact-renamed")
    again = loopcal_main("compact", tmp_path)  # cleans up what the kill left, and finishes
    assert again.returncode == 0, again.stderr
    assert not list(tmp_path.glob(".*.tmp"))
    assert identities(rec.read_recordings(path).scans) == identities(rows)


@pytest.mark.slow
def test_a_file_deleted_while_compacted_stays_deleted(tmp_path):
    """The retention deleting a file during its compaction: the compacted copy must not
    bring it back."""
    path = _recording(tmp_path)
    code = ("import sys; from pathlib import Path; "
            "from loopcal.daemon.recording.compact import compact; "
            "print(compact(Path(sys.argv[1])))")  # fmt: skip
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE,
                            text=True, env={**os.environ,
                                            "LOOPCAL_PAUSE_AT": "compact-verified:3"})  # fmt: skip
    deadline = time.monotonic() + 30
    while not list(tmp_path.glob(".*.compact.tmp")):
        assert time.monotonic() < deadline
        time.sleep(0.05)
    time.sleep(1.0)  # written and being verified or paused after it
    path.unlink()
    out, _ = proc.communicate(timeout=60)
    assert "deleted or replaced" in out and not path.exists()
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.slow
def test_the_recorder_compacts_the_files_it_closes(tmp_path):
    with hand_emulator(rate=50, speed=1.0) as emu:
        proc = record(emu.url, tmp_path, "--rotate-seconds", "2", "--read-period", "0.05")
        proc.wait_for("recording to")
        deadline = time.monotonic() + 30
        first = proc.wait_for("compacted loopcal-", 30)
        proc.wait_for("compacted loopcal-", deadline - time.monotonic(), after=first + 1)
        rc, _ = proc.stop()
    assert rc == 0, proc.text
    out = rec.read_recordings(tmp_path)
    assert_matches_truth(out.scans, emu)
    c = out.scans["counter64"].astype(np.int64)
    assert np.all(np.diff(c) == 1) and out.scans["missed"].sum() == 0
    compacted = [f for f in out.files if "compacted_utc" in f.metadata.get("loopcal", {})]
    assert len(compacted) >= 2 and all(f.intact for f in out.files)
    assert not out.files[-1].metadata["loopcal"].get("compacted_utc")  # the last: at a stop
    # a later start (here with no module answering) takes the file left uncompacted
    again = record("modbus-tcp://127.0.0.1:1", tmp_path, "--duration", "3")
    again.wait(30)
    assert "compacted " + out.files[-1].path.name in again.text


TRIM = """
import numpy as np
from pathlib import Path
from loopcal.daemon.recorder.compactor import release_free_heap

def rss_mb():
    line = next(x for x in Path("/proc/self/status").read_text().splitlines()
                if x.startswith("VmRSS:"))
    return int(line.split()[1]) / 1024

# what a compaction leaves: 190 MB of blocks below malloc's mmap threshold, freed but for
# every 50th, which pins the heap's top
blocks = [np.ones(12_000) for _ in range(2000)]
kept = blocks[::50]
del blocks
before = rss_mb()
print(release_free_heap(), before, rss_mb())
"""


@pytest.mark.slow
def test_the_compactor_gives_what_it_freed_back_to_the_system():
    out = subprocess.run([sys.executable, "-c", TRIM], capture_output=True, text=True,
                         timeout=60, check=True).stdout.split()  # fmt: skip
    trimmed, before, after = out[0] == "True", float(out[1]), float(out[2])
    assert trimmed and before - after > 120, (before, after)


@pytest.mark.slow
def test_the_recorders_compactions_run_in_a_child_whose_crash_costs_only_that_file(
    tmp_path, monkeypatch, caplog
):
    """The daemon's compactor has each file compacted by a child process: a compaction
    killed half way (SIGKILL after its copy is written) leaves this process running, the
    original as it was, and is done again at the next start, which removes what the kill
    left."""
    from loopcal.daemon.recorder.compactor import Compactor

    path = _recording(tmp_path)
    rows = identities(rec.read_recordings(path).scans)
    monkeypatch.setenv("LOOPCAL_KILL_AT", "compact-written")  # in the child, it kills it
    c = Compactor().start()
    c.submit(path)
    c.stop(60)
    assert path not in c.done and path in c._settled  # given up on, this run
    assert "the compaction did not finish: killed by SIGKILL" in caplog.text, caplog.text
    out = rec.read_recordings(path)
    assert identities(out.scans) == rows and out.files[0].intact
    assert "compacted_utc" not in out.files[0].metadata["loopcal"]
    assert list(tmp_path.glob(".*.compact.tmp"))  # what the killed child left
    monkeypatch.delenv("LOOPCAL_KILL_AT")
    again = Compactor().start(tmp_path)
    deadline = time.monotonic() + 60
    while path not in again.done and time.monotonic() < deadline:
        time.sleep(0.1)
    again.stop(60)
    assert path in again.done and not list(tmp_path.glob(".*.tmp"))
    out = rec.read_recordings(path)
    assert identities(out.scans) == rows and "compacted_utc" in out.files[0].metadata["loopcal"]


@pytest.mark.slow
def test_a_compaction_replaces_its_file_only_while_the_directory_is_not_locked(tmp_path):
    """The retention deletes under the directory's lock; a compaction in another process
    waits for it before it checks and replaces the file."""
    from loopcal.daemon.recording.compact import directory_lock

    path = _recording(tmp_path)
    with directory_lock(tmp_path):
        proc = subprocess.Popen([*LOOPCAL, "compact", str(path)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
        deadline = time.monotonic() + 60
        while not list(tmp_path.glob(".*.compact.tmp")):  # written, then it waits to replace
            assert time.monotonic() < deadline and proc.poll() is None, proc.poll()
            time.sleep(0.05)
        time.sleep(1.0)  # and it keeps waiting while the lock is held
        assert proc.poll() is None and "compacted_utc" not in (
            rec.read_recordings(path).files[0].metadata["loopcal"])  # fmt: skip
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0 and "chunks ->" in out, out + err
    assert "compacted_utc" in rec.read_recordings(path).files[0].metadata["loopcal"]


@pytest.mark.slow
def test_the_command_exits_1_when_a_file_fails_and_says_so_in_json(tmp_path):
    good = _recording(tmp_path)
    junk = tmp_path / rec.recording_name(T0 + 10**12)
    junk.write_bytes(b"\x89MCAP0\r\n" + b"not a recording at all" * 10)
    before = junk.read_bytes()
    proc = loopcal_main("compact", tmp_path, "--json")
    assert proc.returncode == 1, proc.stderr
    doc = json.loads(proc.stdout)
    by_path = {f["path"]: f for f in doc["files"]}
    assert by_path[str(good)]["compacted"] and not by_path[str(good)]["failed"]
    assert by_path[str(junk)]["failed"] and not by_path[str(junk)]["compacted"]
    assert doc["failed"] == 1 and doc["bytes_before"] == by_path[str(good)]["bytes_before"]
    assert junk.read_bytes() == before  # kept as it was
    again = loopcal_main("compact", good)  # nothing failed: exit 0
    assert again.returncode == 0 and "already compact" in again.stdout, again.stdout


@pytest.mark.slow
def test_a_second_compaction_leaves_a_running_ones_file_alone(tmp_path):
    """Two `loopcal compact` on one directory: the second neither deletes the first's
    temporary file nor compacts its file; the first then finishes as if alone."""
    path = _recording(tmp_path)
    rows = rec.read_recordings(path).scans
    first = subprocess.Popen([*LOOPCAL, "compact", str(path)], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True,
                             env={**os.environ,
                                  "LOOPCAL_PAUSE_AT": "compact-written:4"})  # fmt: skip
    deadline = time.monotonic() + 30
    while not list(tmp_path.glob(".*.compact.tmp")):
        assert time.monotonic() < deadline and first.poll() is None
        time.sleep(0.05)
    (tmp,) = tmp_path.glob(".*.compact.tmp")
    second = loopcal_main("compact", tmp_path)
    assert second.returncode == 0, second.stderr
    assert "being compacted by another process" in second.stdout, second.stdout
    assert tmp.exists()  # the first one's work was not removed as stale
    out, err = first.communicate(timeout=60)
    assert first.returncode == 0, out + err
    assert "chunks ->" in out
    after = rec.read_recordings(path)
    assert identities(after.scans) == identities(rows) and after.files[0].intact
    assert "compacted_utc" in after.files[0].metadata["loopcal"]
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.slow
def test_two_compactions_at_once_never_crash(tmp_path):
    originals = {}
    for k in range(3):
        path = tmp_path / rec.recording_name(T0 + k * 10**12)
        write_recording(path, make_rows(1200), close=True)
        originals[path] = identities(rec.read_recordings(path).scans)
    for _ in range(4):
        procs = [subprocess.Popen([*LOOPCAL, "compact", str(tmp_path)], text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
                 for _ in range(2)]  # fmt: skip
        for p in procs:
            out, err = p.communicate(timeout=120)
            assert p.returncode == 0 and "Traceback" not in err, out + err
    for path, ids in originals.items():
        out = rec.read_recordings(path)
        assert identities(out.scans) == ids and "compacted_utc" in out.files[0].metadata["loopcal"]
    assert not list(tmp_path.glob(".*.tmp"))


def _views_only_chunk(path) -> int:
    """The file-order index of a chunk holding only view messages (no scan, no event)."""
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    raw = {cid for cid, c in summary.channels.items()
           if c.topic in (rec.TOPIC_SCANS, rec.TOPIC_EVENTS, rec.TOPIC_LOG)}  # fmt: skip
    ordered = sorted(summary.chunk_indexes, key=lambda ci: ci.chunk_start_offset)
    return next(
        k
        for k, ci in enumerate(ordered)
        if ci.message_index_offsets and not set(ci.message_index_offsets) & raw
    )


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["zeroed", "one bit"])
def test_damage_in_the_views_is_never_laundered(tmp_path, damage):
    """A closed file whose damage is in a views-only chunk: the mcap library skips or
    copies what does not check out; compaction must compare with the file's own statistics
    and CRCs, and leave the file as it is, saying it is damaged."""
    path = _recording(tmp_path)
    k = _views_only_chunk(path)
    if damage == "zeroed":
        data = tear_chunk(path, k)
    else:
        off, length = chunk_spans(path.read_bytes())[k]
        data = flip_bits(path.read_bytes(), [(off + length // 2) * 8 + 3])
        path.write_bytes(data)
    r = compact(path)
    assert not r.done and r.failed and r.reason.startswith("damaged"), r
    assert path.read_bytes() == data  # left exactly as it was
    assert not list(tmp_path.glob(".*.tmp"))
    proc = loopcal_main("compact", path)
    assert proc.returncode == 1 and "damaged" in proc.stdout, proc.stdout + proc.stderr


@pytest.mark.slow
def test_a_time_window_of_a_compacted_file_holds_every_scan_inside_it(tmp_path):
    """A block of columns holds a minute, all before its log time: a window that ends
    inside it or starts inside it still gets every scan stamped in it, and only those."""
    path = _recording(tmp_path, n=6600)  # 5.5 minutes
    whole = rec.read_recordings(path).scans
    assert compact(path).done
    stamps = whole["stamp_ns"].astype(np.int64)
    for since_s, until_s in [(0, 10), (30, 95), (59.5, 60.5), (61, 62), (200, 400), (299, 330)]:
        since, until = T0 + int(since_s * 1e9), T0 + int(until_s * 1e9)
        got = rec.read_recordings(path, since=since, until=until)
        want = whole[(stamps >= since) & (stamps < until)]
        assert identities(got.scans) == identities(want), (since_s, until_s)
        assert not got.warnings
