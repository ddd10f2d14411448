"""Scan rows packed column by column: the raw scans of a closed file in a tenth of the bytes.

A ``/daq/scans`` message of a file as written is a ``loopcal_msgs/msg/ScanBlock``: the rows'
own bytes (56 per scan). They compress poorly (2.5x) because each row interleaves fields
of very different statistics. A ``loopcal_msgs/msg/ScanColumns`` message holds the same
rows, every bit of every field, packed for the entropy coder:

1. each field (``codes`` as four channels, each bool as its own column) is read as an
   unsigned integer of its width and differenced ``order`` times (0, 1 or 2, whichever
   leaves the smallest numbers), modulo 2**64, so that any value at all comes back; the
   first value of each difference is kept aside as a seed;
2. the differences are zigzag-coded (small negative numbers become small positive ones)
   and cut into byte planes, only as many planes as the largest needs (a constant column,
   such as a bool that never changes, needs none);
3. the planes of every column, one after the other, are compressed by zstd (with its
   content checksum).

Counters, device times and stamps of a regular module are then almost all zeros; the codes
cost what their scan-to-scan changes carry (about 7 bits a channel at 40 mV of noise).

The message (CDR, little endian)::

    uint32 count   # scans in the block
    uint8 codec    # CODEC (1)
    uint8[] data   # the header and the compressed planes, below

``data``: ``MAGIC``, then one zstd frame (with its content checksum) of: the count again
(uint32); per column, in :data:`COLUMNS` order, its order and plane count (one byte each)
and its ``order`` seeds (uint64 each); the planes. Decoding checks every length, the
count against the message's and the frame's checksum: a damaged message raises
ValueError, never returns rows that were not written.
"""

from __future__ import annotations

import struct

import numpy as np
import zstandard

from ..scan_rows import SCAN_DTYPE
from .schemas import CDR_LE

#: the codec byte of this layout
CODEC = 1
#: the first bytes of ``data``
MAGIC = b"LQC1"
#: the zstd level: compaction runs once per file, in the background; reading is as fast
LEVEL = 19

_UINT = {1: np.uint8, 2: np.uint16, 4: np.uint32, 8: np.uint64}
_U64 = np.uint64


def _columns() -> tuple[tuple[str, int | None, type], ...]:
    """(field, channel or None, unsigned type of its width) of every column."""
    out: list[tuple[str, int | None, type]] = []
    for name in SCAN_DTYPE.names:
        dt, _ = SCAN_DTYPE.fields[name]
        if dt.subdtype is not None:
            base, shape = dt.subdtype
            out += [(name, i, _UINT[base.itemsize]) for i in range(shape[0])]
        else:
            out.append((name, None, _UINT[dt.itemsize]))
    return tuple(out)


#: every column of a block, in the order they are stored
COLUMNS = _columns()
_HEAD = struct.Struct("<I B 3x I")  # count, codec, (CDR padding), the data sequence's length


def _values(rows: np.ndarray, name: str, channel: int | None, kind: type) -> np.ndarray:
    col = rows[name] if channel is None else rows[name][:, channel]
    return np.ascontiguousarray(col).view(kind).astype(_U64)


def _zigzag(d: np.ndarray) -> np.ndarray:
    s = d.view(np.int64)
    return ((s << 1) ^ (s >> 63)).view(_U64)


def _unzigzag(z: np.ndarray) -> np.ndarray:
    one = z.dtype.type(1)
    return (z >> one) ^ (z.dtype.type(0) - (z & one))


def _planes_needed(z: np.ndarray) -> int:
    top = int(z.max()) if len(z) else 0
    return (top.bit_length() + 7) // 8


def _pack_column(x: np.ndarray) -> tuple[int, list[int], np.ndarray]:
    """The order, seeds and zigzagged differences of one column (uint64, wrapping), the
    differences preceded by ``order`` zeros, so that every column of a block has one value
    per scan."""
    best = None
    seeds: list[int] = []
    d = x
    for order in range(min(3, len(x) + 1)):
        if order:
            seeds = [*seeds, int(d[0])]
            d = np.diff(d)  # uint64: modulo 2**64
        z = _zigzag(d)
        cost = float(np.log2(z.astype(np.float64) + 1.0).sum())
        if best is None or cost < best[0]:
            best = (cost, order, list(seeds), z)
    _, order, seeds, z = best
    return order, seeds, np.r_[np.zeros(order, dtype=_U64), z]


def encode_columns(rows: np.ndarray) -> bytes:
    """One ``loopcal_msgs/msg/ScanColumns`` message (CDR) holding ``rows`` (SCAN_DTYPE)."""
    rows = np.ascontiguousarray(rows, dtype=SCAN_DTYPE)
    n = len(rows)
    head = [struct.pack("<I", n)]
    planes = []
    for name, channel, kind in COLUMNS:
        order, seeds, z = _pack_column(_values(rows, name, channel, kind))
        k = _planes_needed(z)
        head.append(struct.pack(f"<BB{order}Q", order, k, *seeds))
        if k:
            planes.append(z.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :k].T.tobytes())
    frame = zstandard.ZstdCompressor(level=LEVEL, write_checksum=True).compress(
        b"".join(head + planes)
    )
    data = MAGIC + frame
    return CDR_LE + _HEAD.pack(n, CODEC, len(data)) + data


def is_columns(message: bytes | memoryview) -> bool:
    """Whether a ``/daq/scans`` message is a ScanColumns block (as opposed to a ScanBlock)."""
    at = len(CDR_LE) + _HEAD.size
    return len(message) >= at + len(MAGIC) and bytes(message[at : at + len(MAGIC)]) == MAGIC


def _parse(message: bytes | memoryview) -> tuple[int, list[tuple[int, int, tuple]], bytes]:
    """(scans, [(order, planes, seeds)] per column, the planes) of one message; ValueError
    saying why it is not a well-formed ScanColumns block."""
    msg = memoryview(message)
    if len(msg) < len(CDR_LE) + _HEAD.size or bytes(msg[:4]) != CDR_LE:
        raise ValueError("scan columns message is not little-endian CDR")
    n, codec, size = _HEAD.unpack_from(msg, 4)
    data = msg[4 + _HEAD.size :]
    if bytes(msg[9:12]) != bytes(3):
        raise ValueError("scan columns message's CDR padding is not zero")
    if codec != CODEC:
        raise ValueError(f"scan columns codec {codec}, this loopcal reads codec {CODEC}")
    if len(data) != size or bytes(data[: len(MAGIC)]) != MAGIC:
        raise ValueError("scan columns message's data length or magic does not check out")
    bound = 4 + len(COLUMNS) * 18 + 8 * len(COLUMNS) * n
    try:
        frame = zstandard.ZstdDecompressor().decompress(bytes(data[len(MAGIC) :]),
                                                        max_output_size=bound)  # fmt: skip
    except zstandard.ZstdError as exc:
        raise ValueError(f"scan columns data does not decompress: {exc}") from None
    if len(frame) < 4 or struct.unpack_from("<I", frame)[0] != n:
        raise ValueError(f"scan columns data is not that of {n} scans")
    pos = 4
    layout = []
    for _ in COLUMNS:
        if pos + 2 > len(frame):
            raise ValueError("scan columns header cut short")
        order, k = frame[pos], frame[pos + 1]
        if order > min(2, n) or k > 8:
            raise ValueError(f"scan columns header: order {order}, {k} planes, {n} scans")
        pos += 2
        if pos + 8 * order > len(frame):
            raise ValueError("scan columns header cut short")
        layout.append((order, k, struct.unpack_from(f"<{order}Q", frame, pos)))
        pos += 8 * order
    want = n * sum(k for _, k, _ in layout)
    if len(frame) - pos != want:
        raise ValueError(f"scan columns data holds {len(frame) - pos} bytes of planes, not {want}")
    return n, layout, memoryview(frame)[pos:]


def _block_cumsum(x: np.ndarray, starts: np.ndarray) -> None:
    """Cumulative sums of ``x`` in place, restarting at each block's first row
    (``starts``, ascending, the first 0), modulo 2**bits of x's dtype: each block's first
    value is lowered by the sum of the block before it (which, so lowered in turn, leaves
    exactly that sum before it), then one cumulative sum."""
    if len(starts) > 1:
        sums = np.add.reduceat(x, starts, dtype=x.dtype)
        x[starts[1:]] -= sums[:-1]
    np.cumsum(x, dtype=x.dtype, out=x)


def _column(z: np.ndarray | None, order: np.ndarray, seeds: list[tuple[int, ...]], n: np.ndarray,
            row_start: np.ndarray, kind: type) -> np.ndarray:  # fmt: skip
    """One column of every block, of unsigned type ``kind``, from its zigzagged differences
    ``z`` (one per row, the first ``order`` of a block zero; None: all zero), orders and
    seeds.

    Arithmetic modulo 2**bits of ``kind`` gives the same values as modulo 2**64: the seeds
    go into the differences (a block's first row gets s0, its second s1 - s0 at order 2),
    so that ``order`` cumulative sums within each block rebuild it. Blocks of a lower order
    than the column's highest are rebuilt and differenced as it wants first."""
    total = int(n.sum())
    if z is None:
        x = np.zeros(total, dtype=kind)
    else:
        d = _unzigzag(z)
        if d.dtype.itemsize < np.dtype(kind).itemsize:  # sign-extend the differences
            signed = np.dtype(f"i{d.dtype.itemsize}")
            d = d.view(signed).astype(f"i{np.dtype(kind).itemsize}")
        x = d.astype(kind, copy=False) if d.dtype == kind else d.astype(kind)
    top = int(order.max())
    if top == 0:
        return x
    bits = 8 * np.dtype(kind).itemsize
    s0 = np.array([s[0] if s else 0 for s in seeds], dtype=np.uint64)
    s1 = np.array([s[1] if len(s) > 1 else 0 for s in seeds], dtype=np.uint64)
    if bits < 64:
        s0 &= np.uint64((1 << bits) - 1)
        s1 &= np.uint64((1 << bits) - 1)
    x[row_start[order >= 1]] = s0[order >= 1].astype(kind)
    two = order == 2
    x[row_start[two] + 1] = (s1[two] - s0[two]).astype(kind)
    for j in np.flatnonzero((order < top) & (n > 0)):
        part = x[int(row_start[j]) : int(row_start[j] + n[j])]
        for _ in range(int(order[j])):
            np.cumsum(part, dtype=kind, out=part)
        for _ in range(top):
            part[1:] = np.diff(part)
    starts = row_start[n > 0]
    for _ in range(top):
        _block_cumsum(x, starts)
    return x


def decode_columns_many(messages: list[bytes | memoryview]) -> tuple[np.ndarray, int]:
    """The rows (SCAN_DTYPE) of ScanColumns messages, in order, and how many did not check
    out (skipped). Every message is checked on its own; the rows of all the good ones are
    then rebuilt at once, column by column: a file's worth in a few numpy calls per column,
    not per message."""
    blocks, bad = [], 0
    for m in messages:
        try:
            blocks.append(_parse(m))
        except (ValueError, struct.error):
            bad += 1
    n = np.array([b[0] for b in blocks], dtype=np.int64)
    total = int(n.sum())
    rows = np.zeros(total, dtype=SCAN_DTYPE)
    if not total:
        return rows, bad
    row_start = np.r_[0, np.cumsum(n)[:-1]]
    at = [0] * len(blocks)  # where each block's next plane starts in its planes
    for c, (name, channel, kind) in enumerate(COLUMNS):
        order = np.array([b[1][c][0] for b in blocks], dtype=np.int64)
        k = [b[1][c][1] for b in blocks]
        wide = np.uint64 if max(k) > 4 else np.uint32 if max(k) > 2 else np.uint16
        z = np.zeros(total, dtype=wide) if max(k) else None
        for p in range(max(k)):
            parts = []
            for j, (nj, _, planes) in enumerate(blocks):
                parts.append(planes[at[j] + p * nj : at[j] + (p + 1) * nj] if k[j] > p
                             else bytes(nj))  # fmt: skip
            plane = np.frombuffer(b"".join(parts), dtype=np.uint8)
            z |= plane.astype(wide) << wide(8 * p) if p else plane
        for j, (nj, _, _) in enumerate(blocks):
            at[j] += k[j] * nj
        if z is None and not order.any():
            continue  # all zero, as the rows are
        x = _column(z, order, [b[1][c][2] for b in blocks], n, row_start, kind)
        if channel is None:
            rows[name] = x.view(rows.dtype.fields[name][0])
        else:
            rows[name][:, channel] = x
    return rows, bad


def decode_columns(message: bytes | memoryview) -> np.ndarray:
    """The rows (SCAN_DTYPE) of one ScanColumns message, bit for bit as encoded.

    Raises
    ------
    ValueError
        If the message is not a well-formed ScanColumns block: its lengths, header, zstd
        frame or checksum do not check out.
    """
    _parse(message)  # raises saying why
    return decode_columns_many([message])[0]


def decode_scan_messages(messages: list[bytes | memoryview]) -> tuple[np.ndarray, int]:
    """The rows (SCAN_DTYPE) of ``/daq/scans`` messages of either layout (ScanBlock as
    written, ScanColumns as compacted), in order, and how many did not check out
    (skipped). Each run of messages of one layout is decoded at once."""
    from .cdr import decode_scan_blocks_checked

    parts, bad = [], 0
    run: list[bytes | memoryview] = []
    columns = False
    for m in [*messages, None]:
        kind = m is not None and is_columns(m)
        if m is None or (run and kind != columns):
            rows, b = decode_columns_many(run) if columns else decode_scan_blocks_checked(run)
            parts.append(rows)
            bad += b
            run = []
        if m is not None:
            run.append(m)
            columns = kind
    rows = np.concatenate(parts) if len(parts) > 1 else parts[0]
    return rows, bad
