"""``loopcal verify``'s check of the chunks: each chunk's header, CRC and records, and the
message indexes after it (:class:`ChunkChecks`, a part of the verifier in
:mod:`~loopcal.daemon.recording.verify`).

Intact chunks whose message indexes all parse are checked in batches through those indexes
with numpy: every entry must point at a message of its channel and log time, and those
messages with the schema and channel records must fill the chunk exactly. A batch that does
not is checked again chunk by chunk, record by record, which says what is wrong and where.
"""

from __future__ import annotations

import struct
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from mcap.opcode import Opcode

from .mcap_records import (
    HEAD,
    MAX_CHUNK_BYTES,
    MESSAGE_FIXED,
    MESSAGE_HEAD,
    MESSAGE_INDEX_ENTRY,
    PARSE_ERRORS,
    RECORD_HEAD,
    checked_chunk,
    chunk_header,
    message_index_entries,
    opcode_name,
    parse_record,
)

#: intact chunks are checked through their message indexes with numpy in batches of this many
#: bytes (decompressed): a file as written has two chunks of some 20 messages each a second
_BATCH_BYTES = 1 << 20
#: what :func:`~loopcal.daemon.recording.mcap_records.checked_chunk` says, as verify names it
_PROBLEMS = {"without CRC": "no CRC written (our writer always writes one)"}


@dataclass(slots=True)
class MessageIndexAt:
    """A message index record after a chunk: its channel and (log time, offset) entries."""

    at: int
    length: int
    channel: int | None = None  # None: the record did not parse
    count: int = 0
    body: bytes = b""  # the entries, 16 bytes each

    def pairs(self) -> list[tuple[int, int]]:
        """The entries as (log time, offset), by offset."""
        return sorted(MESSAGE_INDEX_ENTRY.iter_unpack(self.body), key=lambda e: e[1])


def message_index_at(at: int, length: int, body: memoryview) -> MessageIndexAt:
    """The message index record of ``length`` bytes at byte ``at`` whose body is ``body``
    (its channel None if its fields do not fill it)."""
    try:
        cid, entries = message_index_entries(body)
    except ValueError:
        return MessageIndexAt(at, length)
    return MessageIndexAt(at, length, cid, len(entries) // MESSAGE_INDEX_ENTRY.size,
                          bytes(entries))  # fmt: skip


@dataclass(slots=True)
class ChunkAt:
    """A chunk record of the data section, what it held and the message indexes after it."""

    at: int
    length: int  # the whole record, head included
    start_ns: int | None = None
    end_ns: int | None = None
    compression: str = ""
    compressed_size: int = 0
    uncompressed_size: int = 0
    problem: str = ""  # "" if it checked out
    counts: dict[int, int] = field(default_factory=dict)  # channel id -> messages (intact)
    indexes: list[MessageIndexAt] = field(default_factory=list)
    cut_index: bool = False  # a message index after it was cut off (named on its own)
    raw: bytes | None = None  # its records, decompressed and CRC-checked, until finished
    # (offset, channel id, log time) of its messages, until its indexes are checked
    found: list[tuple[int, int, int]] = field(default_factory=list)

    @property
    def end(self) -> int:
        return self.at + self.length

    @property
    def index_end(self) -> int:
        return self.indexes[-1].at + self.indexes[-1].length if self.indexes else self.end



class ChunkChecks:
    """The verifier's checks of chunks and their message indexes (a mixin of
    :class:`~loopcal.daemon.recording.verify.Verifier`, whose state it shares)."""

    def check_chunk(self, pos: int, whole: int, body: memoryview) -> ChunkAt:
        c = ChunkAt(pos, whole)
        head = chunk_header(body)
        if head is None:
            c.problem = "damaged chunk header (its fields do not fit the record)"
            if len(body) >= 16:
                s, e = struct.unpack_from("<QQ", body, 0)
                if s <= e:
                    c.start_ns, c.end_ns = s, e
            return c
        start, end, usize, _crc, compression, data = head
        c.start_ns, c.end_ns, c.uncompressed_size = start, end, usize
        c.compression, c.compressed_size = compression, len(data)
        raw = checked_chunk(head, strict=self.strict)
        if isinstance(raw, str):
            c.problem = _PROBLEMS.get(raw, raw)
            return c
        c.raw = raw  # its records are checked with its message indexes (finish_chunk)
        return c

    def indexed(self, c: ChunkAt, raw: bytes) -> bool:
        """Queue an intact chunk whose message indexes all parse, one per channel, for
        :meth:`check_batch`; False if they do not (it is then checked record by record)."""
        idx = c.indexes
        if c.cut_index or not idx or any(mi.channel is None or not mi.count for mi in idx) or \
                len({mi.channel for mi in idx}) != len(idx):  # fmt: skip
            return False
        self.batch.append((c, raw))
        self.batch_bytes += len(raw)
        if self.batch_bytes >= _BATCH_BYTES:
            self.check_batch()
        return True

    def check_batch(self) -> None:
        """Check the queued chunks' records through their message indexes, all at once with
        numpy: every entry must point at a message record of its channel and log time, and
        those records, with the others (schemas, channels) walked one by one, must fill each
        chunk exactly, record after record, its messages' log times spanning its header's. If
        anything does not, each chunk of the batch is checked record by record instead
        (:meth:`chunk_records`), which says what is wrong and where."""
        batch, self.batch, self.batch_bytes = self.batch, [], 0
        if batch and not self.batch_checks_out(batch):
            for c, raw in batch:
                c.problem = self.chunk_records(c, raw)
                self.finish_records(c)

    def batch_checks_out(self, batch: list[tuple[ChunkAt, bytes]]) -> bool:
        raw = b"".join(r for _, r in batch)
        sizes = np.array([len(r) for _, r in batch], dtype=np.int64)
        bases = np.concatenate(([0], np.cumsum(sizes)[:-1]))
        indexes = [(k, mi) for k, (c, _) in enumerate(batch) for mi in c.indexes]
        counts = [mi.count for _, mi in indexes]
        entries = np.frombuffer(b"".join(mi.body for _, mi in indexes), dtype="<u8")
        entries = entries.reshape(-1, 2)
        chunk = np.repeat(np.array([k for k, _ in indexes], dtype=np.int64), counts)
        cids = np.repeat(np.array([mi.channel for _, mi in indexes], dtype=np.uint64), counts)
        offs = entries[:, 1].astype(np.int64)
        if (entries[:, 1] > np.uint64(MAX_CHUNK_BYTES)).any() or (
            offs + RECORD_HEAD + MESSAGE_FIXED.size > sizes[chunk]
        ).any():
            return False
        offs += bases[chunk]
        order = np.argsort(offs, kind="stable")
        offs, chunk = offs[order], chunk[order]
        logs, cids = entries[order, 0], cids[order]
        a = np.frombuffer(raw, dtype=np.uint8)
        if (a[offs] != Opcode.MESSAGE).any():
            return False
        lens = _gather(a, offs + 1, "<u8")
        if (lens < MESSAGE_FIXED.size).any() or (lens > np.uint64(MAX_CHUNK_BYTES)).any():
            return False
        ends = offs + RECORD_HEAD + lens.astype(np.int64)
        limits = bases + sizes
        if (ends > limits[chunk]).any() or (ends[:-1] > offs[1:]).any():
            return False
        if (_gather(a, offs + RECORD_HEAD, "<u2") != cids).any():
            return False
        if (_gather(a, offs + RECORD_HEAD + 6, "<u8") != logs).any():
            return False
        firsts = np.flatnonzero(np.diff(chunk, prepend=-1))
        if len(firsts) != len(batch):
            return False
        lasts = np.append(firsts[1:], len(offs)) - 1
        spans = np.column_stack((np.minimum.reduceat(logs, firsts),
                                 np.maximum.reduceat(logs, firsts)))  # fmt: skip
        want = np.array([(c.start_ns, c.end_ns) for c, _ in batch], dtype=np.uint64)
        if not np.array_equal(spans, want):
            return False
        # what lies between the messages: schemas and channels only, filling it exactly
        gaps = np.flatnonzero((ends[:-1] != offs[1:]) & (chunk[:-1] == chunk[1:]))
        between = [(int(ends[i]), int(offs[i + 1])) for i in gaps]
        between += [(int(bases[k]), int(offs[f])) for k, f in enumerate(firsts)
                    if offs[f] != bases[k]]  # fmt: skip
        between += [(int(ends[e]), int(limits[k])) for k, e in enumerate(lasts)
                    if ends[e] != limits[k]]  # fmt: skip
        records = len(offs)
        for lo, hi in sorted(between):
            got = self.other_records(raw, lo, hi)
            if got is None:
                return False
            records += got
        if any(mi.channel not in self.channels for c, _ in batch for mi in c.indexes) and \
                not any(x.problem for x in self.chunks):  # fmt: skip
            return False
        self.out.records += records
        for c, _ in batch:
            c.counts = {mi.channel: mi.count for mi in c.indexes}
            for mi in c.indexes:
                mi.body = b""  # checked: its channel, place and count are what is kept
        return True

    def other_records(self, raw: bytes, lo: int, hi: int) -> int | None:
        """The schema and channel records filling raw[lo:hi] exactly (taken in), or None."""
        p, k = lo, 0
        while p < hi:
            if p + RECORD_HEAD > hi:
                return None
            op, rlen = HEAD.unpack_from(raw, p)
            b = p + RECORD_HEAD
            if op not in (Opcode.SCHEMA, Opcode.CHANNEL) or b + rlen > hi:
                return None
            try:
                rec = parse_record(op, memoryview(raw)[b : b + rlen])
            except PARSE_ERRORS:
                return None
            if op == Opcode.SCHEMA:
                self.schemas.setdefault(rec.id, rec)
            else:
                if rec.schema_id and rec.schema_id not in self.schemas:
                    return None
                self.channels.setdefault(rec.id, rec)
            p, k = b + rlen, k + 1
        return k

    def chunk_records(self, c: ChunkAt, raw: bytes) -> str:
        """Check the records inside an intact chunk one by one, keeping its messages' (offset,
        channel, log time) in ``c.found``; "" or what is wrong."""
        n, p = len(raw), 0
        unpack = MESSAGE_HEAD.unpack_from
        found = c.found
        add = found.append
        records = 0
        try:
            while p < n:
                if p + MESSAGE_HEAD.size <= n:
                    op, rlen, cid, _seq, log, _pub = unpack(raw, p)
                else:
                    op, rlen = HEAD.unpack_from(raw, p)
                records += 1
                if op == Opcode.MESSAGE:
                    if rlen < MESSAGE_FIXED.size or p + MESSAGE_HEAD.size > n:
                        return "a short message record inside"
                    add((p, cid, log))
                elif op in (Opcode.SCHEMA, Opcode.CHANNEL):
                    if self.other_records(raw, p, min(n, p + RECORD_HEAD + rlen)) != 1:
                        return f"a damaged {opcode_name(op)} record inside"
                else:
                    return f"a {opcode_name(op)} record inside"
                p += RECORD_HEAD + rlen
        except struct.error:
            return "its records overrun the chunk"
        if p != n:
            return "its records overrun the chunk"
        self.out.records += records
        if found:
            lo, hi = min(f[2] for f in found), max(f[2] for f in found)
            if (lo, hi) != (c.start_ns, c.end_ns):
                return (f"its header's time span ({c.start_ns}–{c.end_ns} ns) is not its "
                        f"messages' ({lo}–{hi} ns)")  # fmt: skip
        elif (c.start_ns or c.end_ns) and self.strict:
            return "no messages, yet its header gives a time span"
        c.counts = Counter(f[1] for f in found)
        unknown = [cid for cid in c.counts if cid not in self.channels]
        if unknown and not any(x.problem for x in self.chunks):
            return f"messages on channel {unknown[0]}, which no channel record defines"
        return ""

    def finish_chunk(self, c: ChunkAt) -> None:
        """The chunk is complete with its message indexes: check them, and name it if it is
        damaged (its topics and time span from the indexes that describe it)."""
        raw, c.raw = c.raw, None
        if raw is not None and self.indexed(c, raw):
            return  # checked with its batch
        self.check_batch()  # the chunks before it first (their channels, schemas)
        if raw is not None:
            c.problem = self.chunk_records(c, raw)
        self.finish_records(c)

    def finish_records(self, c: ChunkAt) -> None:
        """Check the message indexes of a chunk walked record by record against what it
        held, and name the chunk if it is damaged."""
        found, c.found = c.found, []
        seen: set[int] = set()
        for mi in c.indexes:
            topics = () if mi.channel is None else self.topics_of([mi.channel])
            kw = dict(topics=topics, start_ns=c.start_ns, end_ns=c.end_ns)
            if mi.channel is None:
                self.damage(mi.at, mi.length, "message index",
                            f"its fields do not fit the record (after the chunk at byte {c.at})",
                            topics=self.chunk_topics(c), start_ns=c.start_ns,
                            end_ns=c.end_ns)  # fmt: skip
                continue
            if mi.channel in seen:
                self.damage(mi.at, mi.length, "message index",
                            f"a second index of channel {mi.channel} after the chunk at byte "
                            f"{c.at}", messages=mi.count, **kw)  # fmt: skip
                continue
            seen.add(mi.channel)
            if c.problem:
                continue  # what the chunk held is unknown: the index cannot be checked
            want = [(log, off) for off, cid, log in found if cid == mi.channel]
            got = mi.pairs()
            if got != want:
                self.damage(mi.at, mi.length, "message index",
                            _index_difference(got, want, c.at), messages=mi.count,
                            **kw)  # fmt: skip
        if not c.problem and c.indexes:
            missing = sorted(set(c.counts) - seen)
            if missing and c.cut_index:
                self.cut_topics = self.topics_of(missing)
            elif missing:
                self.damage(c.at, c.length, "chunk",
                            f"no message index for its messages on channel(s) "
                            f"{', '.join(map(str, missing))}", topics=self.topics_of(missing),
                            start_ns=c.start_ns, end_ns=c.end_ns,
                            messages=sum(c.counts[m] for m in missing))  # fmt: skip
        elif not c.problem and found and self.strict:
            self.damage(c.at, c.length, "chunk", "no message index after it",
                        topics=self.topics_of(c.counts), start_ns=c.start_ns, end_ns=c.end_ns,
                        messages=sum(c.counts.values()))  # fmt: skip
        if c.problem:
            indexed = [mi for mi in c.indexes if mi.channel is not None]
            messages = sum(mi.count for mi in indexed) if indexed else None
            ci = self.index_for(c.at, c.end)
            if messages is None and ci is not None and not ci.message_index_offsets:
                messages = 0
            self.damage(c.at, c.length, "chunk", c.problem, topics=self.chunk_topics(c),
                        start_ns=c.start_ns, end_ns=c.end_ns, messages=messages)  # fmt: skip
            if indexed:  # what the damaged chunk held, by its indexes (for the statistics)
                c.counts = Counter({mi.channel: mi.count for mi in indexed})
        for mi in c.indexes:
            mi.body = b""  # checked: its channel, place and count are what is kept

    def chunk_topics(self, c: ChunkAt) -> tuple[str, ...]:
        """The topics of a chunk whose content cannot be trusted: its chunk index entry's
        channels, else its message indexes', else its own messages' (if it decompressed), else
        none."""
        ci = self.index_for(c.at, c.end)
        if ci is not None and ci.chunk_start_offset == c.at and ci.message_index_offsets:
            return self.topics_of(ci.message_index_offsets)
        ids = [mi.channel for mi in c.indexes if mi.channel is not None]
        if ids:
            return self.topics_of(ids)
        return ()


def _gather(a: np.ndarray, offsets: np.ndarray, dtype: str) -> np.ndarray:
    """The little-endian integers of ``dtype`` at byte ``offsets`` of the bytes ``a``."""
    width = np.dtype(dtype).itemsize
    return a[offsets[:, None] + np.arange(width)].view(dtype).ravel()


def _index_difference(
    got: list[tuple[int, int]], want: list[tuple[int, int]], chunk_at: int
) -> str:
    """How a message index's entries (by offset) differ from the chunk's messages."""
    where = f"the chunk at byte {chunk_at}"
    if len(got) != len(want):
        return f"{len(got)} entries, {where} holds {len(want)} message(s) of its channel"
    (glog, goff), (wlog, woff) = next((g, w) for g, w in zip(got, want, strict=True) if g != w)
    if goff != woff:
        return f"an entry points to byte {goff} of {where}, where no message of its channel is"
    return f"an entry gives log time {glog} for the message at byte {goff} of {where} ({wlog})"
