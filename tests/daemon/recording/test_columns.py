"""The raw scans packed column by column (daemon/recording/columns.py): every field of every
scan back bit for bit, whatever the values; damage raises, never yields other rows; the
size on a technician's hour."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.lib.recfunctions import repack_fields

from loopcal.daemon import scan_rows as S
from loopcal.daemon.recording.cdr import encode_scan_block
from loopcal.daemon.recording.columns import (
    decode_columns,
    decode_columns_many,
    decode_scan_messages,
    encode_columns,
    is_columns,
)
from tests.support.fuzz import examples
from tests.support.rows import make_rows, synthetic_rows
from tests.support.sessions import hand_rows


def fields(rows: np.ndarray) -> bytes:
    """Every field's bytes, without the layout's padding."""
    return repack_fields(np.ascontiguousarray(rows)).tobytes()


def any_rows(data: bytes) -> np.ndarray:
    """Rows whose every byte is ``data``'s (bools included: any byte value)."""
    n = len(data) // S.SCAN_DTYPE.itemsize
    return np.frombuffer(data[: n * S.SCAN_DTYPE.itemsize], dtype=S.SCAN_DTYPE).copy()


@pytest.fixture(scope="module")
def hour() -> np.ndarray:
    """An hour of a technician's session at 20 Hz, as the recorder stamps it."""
    return hand_rows(72_000, seed=1)


@settings(max_examples=examples(200), deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(min_size=0, max_size=40 * 56))
def test_any_rows_come_back_bit_for_bit(data):
    rows = any_rows(data)
    message = encode_columns(rows)
    assert is_columns(message) and not is_columns(encode_scan_block(rows))
    assert fields(decode_columns(message)) == fields(rows)


@pytest.mark.slow
@settings(max_examples=examples(60), deadline=None)
@given(st.lists(st.tuples(st.integers(0, 400), st.integers(0, 2**32 - 1)), min_size=1,
                max_size=8))  # fmt: skip
def test_many_blocks_at_once_are_each_block_in_turn(parts):
    """Blocks of every size and content (so of different orders and plane counts per
    column) decoded together give each block's rows, in order."""
    blocks = []
    for n, seed in parts:
        rng = np.random.default_rng(seed)
        kind = seed % 3
        if kind == 0:
            rows = make_rows(n, start=seed % 1000, seed=seed % 7)
        elif kind == 1:
            rows = any_rows(rng.bytes(n * 56))
        else:
            rows = synthetic_rows()[:n]
        blocks.append(rows)
    got, bad = decode_columns_many([encode_columns(b) for b in blocks])
    assert bad == 0
    assert fields(got) == fields(np.concatenate(blocks))


def test_a_replayed_recording_with_wraps_and_restarts_comes_back():
    rows = synthetic_rows()
    assert fields(decode_columns(encode_columns(rows))) == fields(rows)


@pytest.mark.slow
@settings(max_examples=examples(300), deadline=None)
@given(st.integers(0, 2**31))
def test_a_flipped_bit_raises_and_never_yields_other_rows(bit):
    """The frame's checksum covers the header and the planes; CDR's padding must be zero."""
    rows = make_rows(300, seed=2)
    message = bytearray(encode_columns(rows))
    message[(bit // 8) % len(message)] ^= 1 << (bit % 8)
    try:
        got, bad = decode_columns_many([bytes(message)])
    except Exception as exc:  # noqa: BLE001 - what the test is about
        raise AssertionError(f"decode_columns_many raised {exc!r}") from None
    if bad:  # damage seen: nothing of the block comes back
        assert bad == 1 and len(got) == 0
        with pytest.raises(ValueError):
            decode_columns(bytes(message))
    else:  # a bit the decoder does not depend on (in zstd's frame header, say)
        assert fields(got) == fields(rows)


@pytest.mark.slow
def test_a_technicians_hour_takes_under_6_bytes_a_scan(hour):
    messages = [encode_columns(hour[a : a + 1200]) for a in range(0, len(hour), 1200)]
    size = sum(map(len, messages)) / len(hour)
    assert size <= 6.0, f"{size:.2f} B/scan"
    got, bad = decode_columns_many(messages)
    assert bad == 0 and fields(got) == fields(hour)


def test_both_layouts_in_one_file_read_in_order():
    """Rows as written and columns as compacted, mixed, a damaged one among them."""
    rows = make_rows(100)
    messages = [encode_scan_block(rows[:10]), encode_columns(rows[10:50]), b"not a block",
                encode_columns(rows[50:60]), encode_scan_block(rows[60:])]  # fmt: skip
    got, bad = decode_scan_messages(messages)
    assert bad == 1 and fields(got) == fields(rows)
    assert len(decode_scan_messages([])[0]) == 0
