"""A chunked MCAP writer built for surviving damage, on the mcap package's own record types.

mcap's ``Writer`` puts the schema and channel records in the first chunk only (one damaged byte
there hid the whole session), closes chunks by size only (about 15 s of ticks in a 1 MiB chunk),
mixes camera frames with ticks in one chunk (a damaged frame took its ticks with it) and keeps a
``ChunkIndex`` object per chunk until the file closes (about 450 bytes each: closing a chunk a
second would grow a session's memory by 1.6 MB an hour). This layer writes the same records
(``mcap.records``: the file is a plain MCAP file that mcap, Foxglove and our reader read) in a
different order:

* every chunk starts with the schema and channel records of the messages in it (MCAP allows
  them repeated; duplicates are identical), so any chunk can be read on its own;
* a chunk closes at the first of ``chunk_bytes`` and ``chunk_seconds`` of log time, and each
  group of topics (``groups``: e.g. camera frames apart from ticks) has its own chunks, so one
  damaged chunk costs at most about a second of one group;
* every closed chunk is handed to the operating system at once (``flush``): a process killed
  with SIGKILL leaves every closed chunk in the file;
* the chunk index is kept as rows of six integers (48 bytes a chunk) and turned into
  ``ChunkIndex`` records only when the summary is written.

No message indexes are written: readers decompress a chunk whole (mcap, Foxglove and ours read
files without them). The summary names only the channels that carried a message (and their
schemas), so every schema and channel in it also appears in the data section, as MCAP's own
checks (``mcap doctor``) require; a channel that never carried one is named in our metadata's
channel table only.
"""

from __future__ import annotations

import struct
import zlib
from array import array
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import BinaryIO

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, Metadata, MetadataIndex,
                          Schema, Statistics, SummaryOffset)

MAGIC = b"\x89MCAP0\r\n"


def _bytes(builder: RecordBuilder) -> bytes:
    """What a record builder holds, and the builder emptied (mcap's ``end`` has no annotations)."""
    return builder.end()  # type: ignore[no-untyped-call, no-any-return]


@dataclass
class _Open:
    """A chunk being filled: its records (schemas and channels first), its messages' time span."""

    records: RecordBuilder = field(default_factory=RecordBuilder)
    messages: int = 0
    start_ns: int = 0
    end_ns: int = 0
    channels: set[int] = field(default_factory=set)


class SessionWriter:
    """Writes one MCAP file to ``stream`` (see the module docstring)."""

    def __init__(self, stream: BinaryIO, chunk_bytes: int, chunk_seconds: float,
                 groups: Iterable[Iterable[str]] = ()) -> None:
        """``groups``: sets of topics that get chunks of their own; every other topic shares one."""
        self.stream = stream
        self.chunk_bytes = chunk_bytes
        self.chunk_ns = int(chunk_seconds * 1e9)
        self._group_of: dict[str, int] = {t: k + 1 for k, topics in enumerate(groups) for t in topics}
        self._open: dict[int, _Open] = {}
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, Channel] = {}
        self._group_of_channel: dict[int, int] = {}
        self._chunk_rows = array("q")  # per chunk: start ns, end ns, offset, record length, compressed, uncompressed
        self._metadata: list[MetadataIndex] = []
        self._counts: dict[int, int] = {}
        self.message_count = 0
        self._start_ns = 0
        self._end_ns = 0
        self._zstd = zstandard.ZstdCompressor()
        self.chunks_written = 0  # chunks whole on the stream
        self.messages_written: dict[int, int] = {}  # per channel: messages inside chunks whole on the stream

    # -- the file's start ----------------------------------------------------------------
    def start(self, library: str, profile: str = "") -> None:
        builder = RecordBuilder()
        Header(profile=profile, library=library).write(builder)
        self.stream.write(MAGIC + _bytes(builder))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        sid = len(self._schemas) + 1
        self._schemas[sid] = Schema(id=sid, name=name, encoding=encoding, data=data)
        return sid

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        cid = len(self._channels) + 1
        self._channels[cid] = Channel(id=cid, topic=topic, message_encoding=message_encoding, schema_id=schema_id,
                                      metadata={})
        self._group_of_channel[cid] = self._group_of.get(topic, 0)
        self._counts[cid] = 0
        self.messages_written[cid] = 0
        return cid

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record, written at once (outside every chunk)."""
        builder = RecordBuilder()
        offset = self.stream.tell()
        Metadata(name=name, metadata=data).write(builder)
        body = _bytes(builder)
        self.stream.write(body)
        self._metadata.append(MetadataIndex(offset=offset, length=len(body), name=name))
        self.stream.flush()

    # -- messages ------------------------------------------------------------------------
    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int) -> None:
        group = self._group_of_channel[channel_id]
        chunk = self._open.get(group)
        if chunk is not None and chunk.messages and (log_time - chunk.start_ns >= self.chunk_ns
                                                     or chunk.records.count >= self.chunk_bytes):
            self._close(group)
            chunk = None
        if chunk is None:
            chunk = self._open[group] = _Open()
        if channel_id not in chunk.channels:  # what reading this chunk alone needs, first
            channel = self._channels[channel_id]
            if channel.schema_id and not any(self._channels[c].schema_id == channel.schema_id for c in chunk.channels):
                self._schemas[channel.schema_id].write(chunk.records)
            channel.write(chunk.records)
            chunk.channels.add(channel_id)
        Message(channel_id=channel_id, sequence=0, log_time=log_time, publish_time=publish_time,
                data=data).write(chunk.records)
        if chunk.messages == 0:
            chunk.start_ns = chunk.end_ns = log_time
        chunk.start_ns, chunk.end_ns = min(chunk.start_ns, log_time), max(chunk.end_ns, log_time)
        chunk.messages += 1
        self._counts[channel_id] += 1
        if self.message_count == 0:
            self._start_ns = self._end_ns = log_time
        self._start_ns, self._end_ns = min(self._start_ns, log_time), max(self._end_ns, log_time)
        self.message_count += 1

    def _close(self, group: int) -> None:
        """Write the group's open chunk and hand it to the operating system."""
        chunk = self._open.pop(group)
        contents = _bytes(chunk.records)
        compressed = self._zstd.compress(contents)
        builder = RecordBuilder()
        Chunk(compression="zstd", data=compressed, message_start_time=chunk.start_ns, message_end_time=chunk.end_ns,
              uncompressed_crc=zlib.crc32(contents), uncompressed_size=len(contents)).write(builder)
        record = _bytes(builder)
        offset = self.stream.tell()
        self.stream.write(record)
        self.stream.flush()
        self._chunk_rows.extend((chunk.start_ns, chunk.end_ns, offset, len(record), len(compressed), len(contents)))
        self.chunks_written += 1
        for cid in chunk.channels:
            self.messages_written[cid] = self._counts[cid]  # every message so far on this channel is in a closed chunk

    @property
    def message_counts(self) -> dict[int, int]:
        """Messages added so far, per channel id."""
        return dict(self._counts)

    def flush(self) -> None:
        """Close every open chunk now (the writer's queue ran dry, or the session ends)."""
        for group in list(self._open):
            self._close(group)

    # -- the file's end ------------------------------------------------------------------
    def finish(self) -> None:
        """Every open chunk, then the summary (schemas, channels, statistics, chunk and metadata
        indexes), the summary offsets, the footer and the closing magic."""
        self.flush()
        builder = RecordBuilder()
        DataEnd(data_section_crc=0).write(builder)
        self.stream.write(_bytes(builder))
        summary_start = self.stream.tell()
        summary = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode, records: Iterable[Schema | Channel | Statistics | ChunkIndex | MetadataIndex]) -> None:
            start = summary.count
            for r in records:
                r.write(summary)
            if summary.count > start:
                offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                             group_length=summary.count - start))

        # the summary repeats what the data section holds, no more (MCAP's doctor: a channel or
        # schema in the summary must appear in the data section): channels that carried a message
        channels = {cid: c for cid, c in self._channels.items() if self._counts[cid]}
        schemas = {c.schema_id: self._schemas[c.schema_id] for c in channels.values() if c.schema_id}
        group(Opcode.SCHEMA, [schemas[sid] for sid in sorted(schemas)])
        group(Opcode.CHANNEL, channels.values())
        group(Opcode.STATISTICS, [Statistics(
            attachment_count=0, channel_count=len(channels),
            channel_message_counts={cid: self._counts[cid] for cid in channels},
            chunk_count=len(self._chunk_rows) // 6, message_count=self.message_count,
            message_end_time=self._end_ns, message_start_time=self._start_ns, metadata_count=len(self._metadata),
            schema_count=len(schemas))])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes())
        group(Opcode.METADATA_INDEX, self._metadata)
        summary_offset_start = summary_start + summary.count
        for o in offsets:
            o.write(summary)
        data = _bytes(summary)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start),
                         zlib.crc32(data))
        builder = RecordBuilder()
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(builder)
        self.stream.write(data + _bytes(builder) + MAGIC)
        self.stream.flush()

    def _chunk_indexes(self) -> Iterable[ChunkIndex]:
        rows = self._chunk_rows
        for k in range(0, len(rows), 6):
            start, end, offset, length, compressed, uncompressed = rows[k:k + 6]
            yield ChunkIndex(message_start_time=start, message_end_time=end, chunk_start_offset=offset,
                             chunk_length=length, message_index_offsets={}, message_index_length=0,
                             compression="zstd", compressed_size=compressed, uncompressed_size=uncompressed)
