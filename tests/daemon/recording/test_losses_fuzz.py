"""The reader's count of what a damaged file lost, fuzzed: for every mutant, the scans and
events a file's warning says are lost are the scans and events really lost (the unmutated
original's, minus those read), or, where the file cannot tell, at most that many with the
count said to be unknown ("at least N"); never fewer said exactly.

Other seeds and layouts than test_recording_damage.py's fuzz: 1,457 scans of seed 11, 75 a
flush, as closed and as unclosed files.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from loopcal.daemon import recording as rec
from tests.support.fuzz import examples
from tests.support.mutations import MUTATIONS, chunk_spans, flip_bits, identities, zero_run
from tests.support.recordings import write_recording
from tests.support.rows import T0, make_rows

pytestmark = pytest.mark.slow  # docs/architecture.md, "The fast loop"

N, PER = 1457, 75


class _Originals(tuple):
    """(rows, {closed: bytes}, event keys), shown by name (hypothesis prints its
    arguments when an example fails)."""

    def __repr__(self) -> str:
        return f"<{N} scans, {PER} a flush, closed and unclosed>"


@pytest.fixture(scope="module")
def originals(tmp_path_factory):
    """rows, and for closed True/False: the file's bytes and its events' keys."""
    rows = make_rows(N, seed=11)
    d = tmp_path_factory.mktemp("losses")
    out = {}
    for closed in (True, False):
        path = d / f"original-{closed}.mcap"
        write_recording(path, rows, per=PER, close=closed)
        out[closed] = path.read_bytes()
    events = [_event_key(e) for e in rec.read_recordings(path).events]
    return _Originals((rows, out, events))


def _event_key(e: rec.Event) -> tuple[int, str, str]:
    return (e.stamp_ns, e.kind, e.message)


def _tear(data: bytes, k: int, head: int, tail: int) -> bytes:
    """A chunk's data zeroed but for its first ``head`` and last ``tail`` bytes (a torn
    write: its record header intact)."""
    spans = chunk_spans(data)
    off, length = spans[k % len(spans)]
    head = max(9, min(head, length - 1))
    return zero_run(data, off + head, max(1, length - head - min(tail, length - head - 1)))


def _flip_in_chunk(data: bytes, k: int, bit: int) -> bytes:
    """One bit flipped inside chunk ``k`` (in file order, counted from the end if < 0)."""
    off, length = chunk_spans(data)[k]
    return flip_bits(data, [off * 8 + bit % (length * 8)])


def _cut_in_chunk(data: bytes, k: int, at: int) -> bytes:
    """The file cut ``at`` bytes into chunk ``k`` (a write torn by a crash)."""
    off, length = chunk_spans(data)[k]
    return data[: off + at % length]


_MUTANTS = {**MUTATIONS, "tear": _tear, "flip_in_chunk": _flip_in_chunk,
            "cut_in_chunk": _cut_in_chunk}  # fmt: skip
_INT = st.integers(min_value=0, max_value=1 << 30)
MUTATION = st.one_of(
    st.tuples(st.just("flip"), st.lists(st.integers(0, 1 << 28), min_size=1, max_size=4)),
    st.tuples(st.just("truncate"), _INT),
    st.tuples(st.just("zero_run"), _INT, st.integers(1, 20_000)),
    st.tuples(st.just("zero_tail"), _INT, st.integers(1, 20_000)),
    st.tuples(st.just("dup_chunk"), _INT),
    st.tuples(st.just("swap_chunks"), _INT),
    st.tuples(st.just("bad_length"), _INT, st.integers(0, (1 << 64) - 1)),
    st.tuples(st.just("overwrite"), _INT, st.binary(min_size=1, max_size=96)),
    st.tuples(st.just("tear"), _INT, st.integers(0, 400), st.integers(0, 40)),
    st.tuples(st.just("flip_in_chunk"), st.integers(-40, 39), _INT),
)


def _held(original: bytes, mutant: bytes, name: str, args: list) -> int:
    """How many flushes of the original the mutant can hold whole: all of them, but for a
    cut file (zeros after the cut, or not) only those whose raw chunk ends before the cut:
    a file cut inside a record that holds no scan looks like a recorder that stopped
    there, and nothing in it says more was written."""
    flushes = chunk_spans(original)[0::2]  # each flush: a raw chunk, then a views chunk
    if name not in ("truncate", "zero_tail", "cut_in_chunk"):
        return len(flushes)
    kept = args[0] % (len(original) + 1) if name == "zero_tail" else len(mutant)
    return sum(off + n <= kept for off, n in flushes)


def _judge_counts(rows, events, original: bytes, mutation: tuple, path) -> None:
    name, *args = mutation
    mutant = _MUTANTS[name](original, *args)
    path.write_bytes(mutant)
    try:
        out = rec.read_recordings(path)
    except rec.RecordingError:
        return  # declared: test_recording_damage.py's fuzz judges that
    got = identities(out.scans)
    assert len(set(got)) == len(got) and set(got) <= set(identities(rows))
    held = _held(original, mutant, name, args)
    scans_held = min(len(rows), held * PER)
    lost = scans_held - len(got)  # a cut file gives none of the flushes it cannot hold
    last = int(rows["stamp_ns"][scans_held - 1]) if scans_held else None
    keys_held = {k for k in events if last is not None and k[0] <= last}
    events_lost = len(keys_held - {_event_key(e) for e in out.events})
    [f] = out.files
    said = (f.lost_scans, f.lost_unknown, f.lost_events, f.lost_events_unknown, f.warning)
    if f.lost_unknown:
        assert f.lost_scans <= lost, said
        assert "at least" in f.warning or "unknown number of scans" in f.warning, said
    else:
        assert f.lost_scans == lost, said
        if lost:
            assert f"{lost} scan(s) missing" in f.warning, said
    if lost or f.lost_unknown:
        assert "no scan lost" not in f.warning, said
    if f.lost_events_unknown:
        assert f.lost_events <= events_lost, said
    else:
        assert f.lost_events == events_lost, said
    if rec.message_time_range(path) is not None and "loopcal" in f.metadata:
        # statistics trusted, of a file known to be ours: the counts are exact
        assert not f.lost_unknown and not f.lost_events_unknown, said


_FIXTURES_OK = [HealthCheck.function_scoped_fixture]  # tmp_path is reused: each example rewrites


@settings(max_examples=examples(150), deadline=None, suppress_health_check=_FIXTURES_OK)
@given(closed=st.booleans(), mutation=MUTATION)
@example(closed=False, mutation=("tear", 196, 353, 0))
@example(closed=True, mutation=("swap_chunks", 7))  # was 401 of 1,457 scans lost, declared
@example(closed=True, mutation=("flip_in_chunk", 0, 1600))  # first chunk: 75 lost, same words
@example(closed=False, mutation=("flip_in_chunk", 0, 1600))
@example(closed=False, mutation=("flip_in_chunk", -2, 1600))  # the last raw chunk
@example(closed=False, mutation=("zero_run", 340, 13_000))  # the first flush, both its chunks
@example(closed=False, mutation=("cut_in_chunk", -2, 300))  # cut inside the last raw chunk
def test_the_loss_a_warning_counts_is_the_loss(originals, tmp_path, closed, mutation):
    rows, data, events = originals
    _judge_counts(rows, events, data[closed], mutation, tmp_path / rec.recording_name(T0))
