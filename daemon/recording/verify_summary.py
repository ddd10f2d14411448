"""``loopcal verify``'s check of the summary section against the data section: schemas and
channels, every chunk index entry against its chunk, the metadata indexes, the summary
offsets and the statistics against the counts found (:class:`SummaryChecks`, a part of
the verifier in :mod:`~loopcal.daemon.recording.verify`).
"""

from __future__ import annotations

from collections import Counter

from mcap.opcode import Opcode
from mcap.records import ChunkIndex

from .mcap_records import DATA_END_BYTES, FOOTER_BYTES, opcode_name
from .verify_chunks import ChunkAt


class SummaryChecks:
    """The verifier's checks of the summary against what the data section held (a mixin of
    :class:`~loopcal.daemon.recording.verify.Verifier`, whose state it shares)."""

    def check_summary(self) -> None:
        if self.footer is None or not self.footer.summary_start:
            return  # no summary to check (its absence is named)
        footer = self.footer
        if self.data_end_at is not None and footer.summary_start != self.data_end_at + \
                DATA_END_BYTES:  # fmt: skip
            self.damage(self.footer_at, FOOTER_BYTES, "footer",
                        f"summary start {footer.summary_start} is not where the data end "
                        f"record ends ({self.data_end_at + DATA_END_BYTES})")  # fmt: skip
        offsets_group = self.s_groups.get(Opcode.SUMMARY_OFFSET, [])
        want_offsets = offsets_group[0][0] if offsets_group else 0
        if self.s_parsed_to is None and footer.summary_offset_start != want_offsets:
            self.damage(self.footer_at, FOOTER_BYTES, "footer",
                        f"summary offsets start at byte {want_offsets}, the footer says "
                        f"{footer.summary_offset_start}")  # fmt: skip
        self.check_schemas_and_channels()
        self.check_chunk_indexes()
        self.check_metadata_indexes()
        self.check_summary_offsets()
        self.check_statistics()

    def check_schemas_and_channels(self) -> None:
        for group, ours, theirs in ((Opcode.SCHEMA, self.schemas, self.s_schemas),
                                    (Opcode.CHANNEL, self.channels, self.s_channels)):  # fmt: skip
            places = dict(zip(theirs, self.s_groups.get(group, []), strict=False))
            for rid, rec in theirs.items():
                mine = ours.get(rid)
                if mine is not None and mine != rec:
                    at, length = places.get(rid, (self.footer.summary_start, 0))
                    topics = (rec.topic,) if group == Opcode.CHANNEL else ()
                    self.damage(at, length, opcode_name(group),
                                f"{opcode_name(group)} {rid} differs from the data section's",
                                topics=topics)  # fmt: skip
            if self.strict and self.s_parsed_to is None and not any(c.problem for c in self.chunks):
                for rid in set(ours) - set(theirs):
                    self.damage(
                        self.footer.summary_start,
                        0,
                        "summary",
                        f"{opcode_name(group)} {rid} of the data section is not in the summary",
                    )

    def check_chunk_indexes(self) -> None:
        chunks = {c.at: c for c in self.chunks}
        by_order = len(self.s_chunk_indexes) == len(self.chunks)
        described: set[int] = set()
        for k, (ci, (at, length)) in enumerate(zip(self.s_chunk_indexes, self.s_index_places,
                                                        strict=True)):
            c = chunks.get(ci.chunk_start_offset)
            meant = c if c is not None else (self.chunks[k] if by_order else None)
            if c is None and self.in_unreadable(ci.chunk_start_offset):
                continue  # the stretch it points into is named damaged

            def described_by(ci: ChunkIndex = ci, meant: ChunkAt | None = meant) -> dict:
                """The topics and span of the chunk an entry describes: that chunk's own when
                it checked out, else the entry's."""
                if meant is not None and not meant.problem and meant.counts:
                    return dict(topics=self.topics_of(meant.counts), start_ns=meant.start_ns,
                                end_ns=meant.end_ns)  # fmt: skip
                return dict(topics=self.topics_of(ci.message_index_offsets),
                            start_ns=ci.message_start_time, end_ns=ci.message_end_time)  # fmt: skip

            if c is None:
                where = f" (the chunk at byte {meant.at}?)" if meant is not None else ""
                self.damage(at, length, "chunk index",
                            f"points to byte {ci.chunk_start_offset}, where no chunk starts{where}",
                            **described_by())  # fmt: skip
                continue
            described.add(c.at)
            if c.problem:
                continue  # the chunk is named damaged; its fields cannot be checked
            wrong = []
            if ci.chunk_length != c.length:
                wrong.append(f"chunk length {ci.chunk_length}, not {c.length}")
            if (ci.message_start_time, ci.message_end_time) != (c.start_ns, c.end_ns):
                wrong.append(f"time span {ci.message_start_time}–{ci.message_end_time} ns, not "
                             f"{c.start_ns}–{c.end_ns}")  # fmt: skip
            if ci.compression != c.compression:
                wrong.append(f"compression {ci.compression!r}, not {c.compression!r}")
            if ci.compressed_size != c.compressed_size:
                wrong.append(f"compressed size {ci.compressed_size}, not {c.compressed_size}")
            if ci.uncompressed_size != c.uncompressed_size:
                wrong.append(f"uncompressed size {ci.uncompressed_size}, not "
                             f"{c.uncompressed_size}")  # fmt: skip
            indexes = {mi.channel: mi.at for mi in c.indexes if mi.channel is not None}
            if ci.message_index_offsets != indexes:
                wrong.append(f"message index offsets {_mapping(ci.message_index_offsets)}, "
                             f"not {_mapping(indexes)}")  # fmt: skip
            if ci.message_index_length != c.index_end - c.end:
                wrong.append(f"message index length {ci.message_index_length}, not "
                             f"{c.index_end - c.end}")  # fmt: skip
            if wrong:
                self.damage(at, length, "chunk index",
                            f"for the chunk at byte {c.at}: " + "; ".join(wrong),
                            messages=sum(c.counts.values()), **described_by())  # fmt: skip
        if self.strict and self.s_parsed_to is None:
            for c in self.chunks:
                if c.at not in described and not c.problem:
                    self.damage(c.at, c.length, "chunk", "not in the summary's chunk index",
                                topics=self.topics_of(c.counts), start_ns=c.start_ns,
                                end_ns=c.end_ns, messages=sum(c.counts.values()))  # fmt: skip

    def in_unreadable(self, at: int) -> bool:
        return any(d.record in ("records", "chunk") and d.offset <= at < d.offset + d.length
                   for d in self.damaged)  # fmt: skip

    def check_metadata_indexes(self) -> None:
        indexed = set()
        for at, length, mi in self.s_metadata_indexes:
            got = self.metadata.get(mi.offset)
            if got is None:
                self.damage(at, length, "metadata index",
                            f"points to byte {mi.offset}, where no intact metadata record "
                            f"starts (name {mi.name!r})")  # fmt: skip
            elif (got[0], got[1]) != (mi.length, mi.name):
                self.damage(at, length, "metadata index",
                            f"says {mi.name!r} of {mi.length} bytes at byte {mi.offset}; the "
                            f"record there is {got[1]!r} of {got[0]} bytes")  # fmt: skip
            indexed.add(mi.offset)
        if self.strict and self.s_parsed_to is None:
            for at, (length, name, _) in self.metadata.items():
                if at not in indexed:
                    self.damage(at, length, "metadata", f"{name!r} is not in the summary's "
                                "metadata index")  # fmt: skip

    def check_summary_offsets(self) -> None:
        if self.s_parsed_to is not None:
            return
        named = set()
        for at, length, so in self.s_offsets:
            group = self.s_groups.get(so.group_opcode, [])
            start = group[0][0] if group else so.group_start
            size = sum(g[1] for g in group)
            contiguous = all(a + n == b for (a, n), (b, _) in zip(group, group[1:], strict=False))
            if so.group_opcode in named or (so.group_start, so.group_length) != (start, size) \
                    or not contiguous:  # fmt: skip
                self.damage(at, length, "summary offset",
                            f"the {opcode_name(so.group_opcode)} group at byte {so.group_start} of "
                            f"{so.group_length} bytes; the summary's is at byte {start} of "
                            f"{size}")  # fmt: skip
            named.add(so.group_opcode)

    def check_statistics(self) -> None:
        if self.s_statistics is None:
            if self.strict and self.s_parsed_to is None:
                self.damage(self.footer.summary_start, 0, "summary", "no statistics record")
            return
        at, length, st = self.s_statistics
        if (
            any(c.problem and not c.counts for c in self.chunks)
            or self.unreadable
            or self.s_parsed_to is not None
        ):
            return  # what a damaged chunk held is unknown: the counts cannot be checked
        counts: Counter = Counter()
        for c in self.chunks:
            counts.update(c.counts)
        stats = Counter({k: v for k, v in st.channel_message_counts.items()})
        wrong, topics = [], set()
        diff = 0
        for cid in sorted(set(counts) | set(stats)):
            if counts[cid] != stats[cid]:
                t = self.topics_of([cid])[0]
                topics.add(t)
                diff += abs(counts[cid] - stats[cid])
                wrong.append(f"{t} {stats[cid]} message(s), found {counts[cid]}")
        total = sum(counts.values())
        if st.message_count != total:
            wrong.append(f"message count {st.message_count}, found {total}")
        if st.chunk_count != len(self.chunks):
            wrong.append(f"chunk count {st.chunk_count}, found {len(self.chunks)}")
        if st.metadata_count != len(self.metadata):
            wrong.append(f"metadata count {st.metadata_count}, found {len(self.metadata)}")
        if st.attachment_count != 0:
            wrong.append(f"attachment count {st.attachment_count}, found 0")
        schemas = set(self.schemas) | set(self.s_schemas)
        channels = set(self.channels) | set(self.s_channels)
        if st.schema_count != len(schemas):
            wrong.append(f"schema count {st.schema_count}, found {len(schemas)}")
        if st.channel_count != len(channels):
            wrong.append(f"channel count {st.channel_count}, found {len(channels)}")
        spans = [(c.start_ns, c.end_ns) for c in self.chunks if c.counts and c.start_ns is not None]
        if spans:
            lo, hi = min(s for s, _ in spans), max(e for _, e in spans)
            if (st.message_start_time, st.message_end_time) != (lo, hi):
                wrong.append(f"time span {st.message_start_time}–{st.message_end_time} ns, "
                             f"found {lo}–{hi}")  # fmt: skip
        if wrong:
            lo = st.message_start_time if st.message_count else None
            self.damage(at, length, "statistics", "; ".join(wrong), topics=tuple(sorted(topics)),
                        start_ns=lo, end_ns=st.message_end_time if lo is not None else None,
                        messages=diff or None)  # fmt: skip


def _mapping(d: dict[int, int]) -> str:
    return "{" + ", ".join(f"{k}: {v}" for k, v in sorted(d.items())) + "}"
