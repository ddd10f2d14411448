"""Older files without their views: compaction with ``drop_views`` keeps every raw scan and
event bit for bit in about a twentieth of the bytes, says so in the file, reads everywhere,
counts what damage loses as exactly as a file with views, and the daemon does it by itself
to files past ``[recording].keep_views_days``."""

from __future__ import annotations

import json
import math
import shutil
import struct
import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from loopcal.daemon import recording as rec
from loopcal.daemon.recorder.compactor import DAY_S, Compactor
from loopcal.daemon.recording.compact import DROPPED_VIEWS, compact
from loopcal.daemon.recording.verify import verify_file
from tests.support.emulator import hand_emulator
from tests.support.fuzz import examples
from tests.support.js import read_ts
from tests.support.mutations import chunk_spans, flip_bits, identities, swap_chunks, zero_run
from tests.support.processes import loopcal_main, record
from tests.support.recordings import in_large_chunks, write_recording
from tests.support.rows import T0
from tests.support.sessions import hand_rows

pytestmark = pytest.mark.timeout(180)

#: ten minutes of a technician's hand motion at 20 Hz
N = 12_000


@pytest.fixture(scope="module")
def thinned(tmp_path_factory):
    """(rows, the file as written, a compacted copy without its views)."""
    d = tmp_path_factory.mktemp("thinned")
    rows = hand_rows(N, seed=5)
    written = d / "written" / rec.recording_name(T0)
    written.parent.mkdir()
    write_recording(written, rows, per=20)
    copy = d / "thin" / written.name
    copy.parent.mkdir()
    shutil.copy(written, copy)
    r = compact(copy, drop_views=True)
    assert r.done, r.reason
    return rows, written, copy


def _counts(path) -> dict[str, int]:
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    stats = summary.statistics.channel_message_counts
    return {c.topic: stats.get(i, 0) for i, c in summary.channels.items()}


@pytest.mark.slow
def test_every_scan_and_event_stays_in_a_twentieth_of_the_bytes(thinned, node_reader):
    rows, written, thin = thinned
    before, after = rec.read_recordings(written), rec.read_recordings(thin)
    assert identities(after.scans) == identities(before.scans) == identities(rows)
    assert [e.to_json() for e in after.events] == [e.to_json() for e in before.events]
    [f] = after.files
    assert f.complete and f.intact and not f.warning
    record_ = f.metadata["loopcal"]
    assert record_["views"] == "dropped" and record_["scans"] == str(N)
    assert record_["format"] == rec.COMPACT_FORMAT and "views_dropped_utc" in record_
    per_scan = thin.stat().st_size / N
    print(f"\n  {written.stat().st_size / N:.1f} B/scan as written, {per_scan:.2f} without views")
    assert per_scan <= 12  # issue 20's target for a closed file
    was, now = _counts(written), _counts(thin)
    assert all(now[t] == 0 for t in DROPPED_VIEWS) and was[rec.TOPIC_STATE] == N
    assert now[rec.TOPIC_SCENE] == was[rec.TOPIC_SCENE] == 1
    assert now[rec.TOPIC_EVENTS] == was[rec.TOPIC_EVENTS]
    with open(thin, "rb") as fh:  # the mcap library reads every message, CRCs checked
        n = sum(1 for _ in make_reader(fh, validate_crcs=True).iter_messages())
    assert n == sum(now.values())
    ts = read_ts(node_reader, thin)  # Foxglove's reader too
    assert ts["packedScans"] == N
    proc = loopcal_main("verify", thin, "--json")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    again = compact(thin, drop_views=True)
    assert not again.done and again.reason == "already compact"
    info = json.loads(loopcal_main("info", thin, "--json").stdout)
    assert info["files"][0]["views"] is False and info["scans"] == N
    assert "views left out (loopcal export makes them)" in loopcal_main("info", thin).stdout
    assert json.loads(loopcal_main("info", written, "--json").stdout)["files"][0]["views"]


@pytest.mark.slow
def test_a_compact_file_with_views_is_thinned_again_and_the_command_says_so(thinned, tmp_path):
    rows, written, _ = thinned
    path = tmp_path / written.name
    shutil.copy(written, path)
    assert compact(path).done  # as the daemon keeps a new file: compact, with its views
    assert _counts(path)[rec.TOPIC_STATE] == N
    proc = loopcal_main("compact", path, "--drop-views", "--json")
    assert proc.returncode == 0, proc.stderr
    [doc] = json.loads(proc.stdout)["files"]
    assert doc["compacted"] and doc["bytes_after"] <= 12 * N < doc["bytes_before"]
    out = rec.read_recordings(path)
    assert identities(out.scans) == identities(rows) and out.files[0].intact
    # a minute of scans at most in any chunk, as in a file compacted once
    spans = []
    with open(path, "rb") as f:
        for ci in make_reader(f).get_summary().chunk_indexes:
            spans.append(ci.message_end_time - ci.message_start_time)
    scans = out.scans["stamp_ns"]
    assert max(spans) <= 60 * 10**9
    assert len(chunk_spans(path.read_bytes())) >= (scans[-1] - scans[0]) / 60e9


def _lost_said(path) -> tuple[int, bool, int]:
    out = rec.read_recordings(path)
    [f] = out.files
    return f.lost_scans, bool(f.lost_unknown), len(out.scans)


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["flip", "zeros", "swap"])
def test_what_damage_costs_is_counted_against_the_files_own_count(thinned, tmp_path, damage):
    """Without views nothing describes each scan but the raw chunks; the file's own count
    (the loopcal record's ``scans``) still makes the loss exact, the first and last chunks
    included."""
    _, _, thin = thinned
    data = thin.read_bytes()
    spans = chunk_spans(data)
    path = tmp_path / thin.name
    for k in range(len(spans)):
        off, length = spans[k]
        if damage == "flip":
            mutant = flip_bits(data, [(off + length // 2) * 8 + 3])
        elif damage == "zeros":
            mutant = zero_run(data, off + 40, length - 60)
        else:
            mutant = swap_chunks(data, k)
        path.write_bytes(mutant)
        lost, unknown, read = _lost_said(path)
        assert not unknown and lost == N - read, (k, lost, N - read)
        assert N - read <= 60 * 20  # one damaged chunk costs a minute at most


@pytest.mark.slow
@settings(max_examples=examples(60), deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])  # fmt: skip
@given(mutation=st.one_of(
    st.tuples(st.just("flip"), st.lists(st.integers(0, 1 << 28), min_size=1, max_size=4)),
    st.tuples(st.just("zeros"), st.integers(0, 1 << 30), st.integers(1, 20_000)),
))  # fmt: skip
def test_the_loss_a_warning_counts_is_the_loss_without_views(thinned, tmp_path, mutation):
    rows, _, thin = thinned
    data = thin.read_bytes()
    name, *args = mutation
    if name == "flip":
        mutant = flip_bits(data, [p % (len(data) * 8) for p in args[0]])
    else:
        mutant = zero_run(data, args[0] % len(data), args[1])
    path = tmp_path / thin.name
    path.write_bytes(mutant)
    try:
        out = rec.read_recordings(path)
    except rec.RecordingError:
        return  # declared
    got = identities(out.scans)
    assert len(set(got)) == len(got) and set(got) <= set(identities(rows))
    [f] = out.files
    lost = N - len(got)
    if f.lost_unknown:
        assert f.lost_scans <= lost and f.warning, f.warning
    else:
        assert f.lost_scans == lost, (f.lost_scans, lost, f.warning)
    if lost:
        assert f.warning


@pytest.mark.slow
@pytest.mark.parametrize("views", [True, False])
def test_a_record_length_that_skips_the_first_chunk_is_not_taken_for_no_loss(
    thinned, tmp_path, views
):
    """ci48, in bytes that do not depend on the run: the header's length carries the walk
    from the start into the third chunk, the first chunk is damaged, and the summary's
    CRC fails. The walk lands in the middle of an intact chunk; the reader once reported
    "no valid record" there, inside the scans it read, and so no scan lost while the first
    minute (and the record that counts the scans) was gone."""
    rows, written, thin = thinned
    data = (written if views else thin).read_bytes()
    (a, na), _, (b, nb) = chunk_spans(data)[:3]
    out = bytearray(flip_bits(data, [(a + na // 2) * 8]))
    land = next(x for x in range(b + nb // 2, b + nb) if 0x0F < data[x] < 0x80)  # no opcode
    struct.pack_into("<Q", out, 9, land - 17)  # the header record: opcode at 8
    out[-8 - 4] ^= 1  # the footer's summary CRC
    path = tmp_path / written.name
    path.write_bytes(bytes(out))
    got = rec.read_recordings(path)
    [f] = got.files
    assert len(got.scans) < N
    assert f.lost_unknown or f.lost_scans == N - len(got.scans), f.warning
    assert f.lost_scans <= N - len(got.scans)
    assert "ran past an intact chunk" in f.warning and "no scan lost" not in f.warning
    [header] = [d for d in verify_file(path).damaged if d.offset == 8]  # verify names it too
    assert header.record == "header" and "runs past the intact chunk" in header.what


@pytest.mark.slow
def test_a_wrong_count_in_the_loopcal_record_is_not_taken_for_lost_scans(thinned, tmp_path):
    """ci51: no CRC covers a metadata record. A digit of the loopcal record's count flipped
    (12000 to 12100), and the record after it damaged, was read as 100 scans lost, every
    chunk the index lists intact. Damage that cannot hold a scan leaves the count wrong,
    not the scans lost."""
    _, _, thin = thinned
    data = bytearray(thin.read_bytes())
    count = data.find(b"\x05\x00\x00\x00scans\x05\x00\x00\x0012000")
    assert count > 0
    data[count + 9 + 4 + 2] ^= 1  # "12000" -> "12100"
    device = data.find(b"\x06\x00\x00\x00device") - 9  # its opcode; the length follows
    assert data[device] == 0x0C  # a metadata record
    data[device + 2] ^= 1
    path = tmp_path / thin.name
    path.write_bytes(bytes(data))
    out = rec.read_recordings(path)
    [f] = out.files
    assert len(out.scans) == N and f.lost_scans == 0 and not f.lost_unknown, f.warning
    assert "the loopcal record counts 100 scan(s) more than the intact chunks hold" in f.warning
    assert "no scan lost" in f.warning


def _named(directory, days_ago: float, rows) -> object:
    path = directory / rec.recording_name(time.time_ns() - int(days_ago * DAY_S * 1e9))
    write_recording(path, rows, per=20)
    return path


@pytest.mark.slow
def test_the_daemons_compactor_thins_the_files_past_their_age(tmp_path):
    rows = hand_rows(2400, seed=6)
    old, older, recent, newest = (_named(tmp_path, d, rows) for d in (8, 30, 1, 0))
    c = Compactor(lambda: 7.0).start(tmp_path)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and len(c.done) < 4:
        time.sleep(0.1)
    c.stop(10)
    assert sorted(c.done) == sorted([old, older, recent, newest])
    for path, dropped in ((old, True), (older, True), (recent, False), (newest, False)):
        record_ = rec.read_recordings(path).files[0].metadata["loopcal"]
        assert record_["format"] == rec.COMPACT_FORMAT
        assert (record_.get("views") == "dropped") is dropped, path.name
        assert identities(rec.read_recordings(path).scans) == identities(rows)
    # a file that crosses the age while the daemon runs is thinned after the next rotation
    later = Compactor(lambda: 0.5)
    later.start(tmp_path)
    nxt = _named(tmp_path, 0, rows)
    later.submit(nxt)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and recent not in later.done:
        time.sleep(0.1)
    later.stop(10)
    assert rec.read_recordings(recent).files[0].metadata["loopcal"]["views"] == "dropped"
    assert "views" not in rec.read_recordings(nxt).files[0].metadata["loopcal"]
    assert not Compactor(lambda: math.inf).views_expired(older)
    # a file the retention removed is forgotten, so a daemon of months remembers no more
    # files than its directory holds
    assert older in later._settled
    older.unlink()
    assert later._expired_in_directory() == [] and older not in later._settled
    assert recent in later._settled


@pytest.mark.slow
def test_the_recorder_thins_what_it_closes_when_told_to_keep_no_views(tmp_path):
    with hand_emulator(rate=50, speed=1.0) as emu:
        proc = record(emu.url, tmp_path, "--rotate-seconds", "2", "--read-period", "0.05",
                      "--keep-views-days", "0")  # fmt: skip
        proc.wait_for("recording to")
        proc.wait_for("compacted loopcal-.* without its views", 30)
        rc, _ = proc.stop()
    assert rc == 0, proc.text
    out = rec.read_recordings(tmp_path)
    thin = [f for f in out.files if f.metadata.get("loopcal", {}).get("views") == "dropped"]
    assert thin and all(f.intact for f in out.files)
    assert all(f.metadata["loopcal"]["scans"] == str(f.scans) for f in thin)


@pytest.mark.slow
@pytest.mark.parametrize("value", ["-1", "nan", "soon"])
def test_a_bad_age_is_refused_naming_the_option(tmp_path, value):
    proc = loopcal_main("record", "--daq", "modbus-tcp://127.0.0.1:1", "--out", tmp_path,
                   "--keep-views-days", value, "--duration", "1")  # fmt: skip
    assert proc.returncode == 2 and "--keep-views-days" in proc.stderr, proc.stderr


@pytest.mark.slow
def test_every_older_layout_reads_and_thins(thinned, tmp_path):
    """Files as written (format 1), compacted by the first loopcal that compacted (format 1,
    rows in chunks of 4 MiB), compacted with views (format 2) and without: the same scans
    from each, and each older one thinned to the newest layout."""
    rows, written, thin = thinned
    old = tmp_path / "old" / written.name
    old.parent.mkdir()
    assert rec.read_recordings(written).files[0].metadata["loopcal"]["format"] == "1"
    in_large_chunks(written, old, lambda r: r.update(compacted_utc="2026-11-20T00:00:00+00:00"))
    with_views = tmp_path / "views" / written.name
    with_views.parent.mkdir()
    shutil.copy(written, with_views)
    assert compact(with_views).done
    as_written = tmp_path / "written" / written.name
    as_written.parent.mkdir()
    shutil.copy(written, as_written)
    for path in (as_written, old, with_views, thin):
        out = rec.read_recordings(path)
        assert identities(out.scans) == identities(rows), path.parent.name
        assert out.files[0].intact and not out.files[0].warning, path.parent.name
    for path in (as_written, old, with_views):
        r = compact(path, drop_views=True)
        assert r.done, (path.parent.name, r.reason)
        assert path.read_bytes()[:8] == thin.read_bytes()[:8]
        out = rec.read_recordings(path)
        assert identities(out.scans) == identities(rows)
        assert out.files[0].metadata["loopcal"]["views"] == "dropped"
        assert abs(path.stat().st_size - thin.stat().st_size) < 0.02 * thin.stat().st_size
