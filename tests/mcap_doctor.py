"""MCAP's own structural checks (what ``mcap doctor`` checks), from the MCAP specification's
record layout: a file's errors as a list of lines, empty for a good file.

The ``mcap`` package reads and writes but has no doctor, so the checks are here, on its
record types: magic at both ends; the header first; records parse to their exact lengths;
in the data section only the records MCAP allows there; every chunk decompresses to its
size and CRC and holds only schemas, channels and messages, each message on a channel (and
that channel's schema) announced before it, its log time within the chunk's start and end;
message indexes (if any) right after their chunk, each entry at a message with that log
time; after the data end record, every schema and channel of the summary also in the data
section and equal to it; each chunk index at a chunk record with the same length, times,
compression and sizes, and every chunk indexed, its channels and schemas in the summary;
one statistics record whose counts, times and per-channel counts are what the file holds;
summary offsets at groups of their opcode; metadata indexes at metadata records of their
name; the footer's summary CRC.
"""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path
from typing import Any

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.records import (Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, Message, MessageIndex, Metadata,
                          MetadataIndex, Schema, Statistics, SummaryOffset)

MAGIC = b"\x89MCAP0\r\n"
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, CHUNK_INDEX = 1, 2, 3, 4, 5, 6, 7, 8
ATTACHMENT, ATTACHMENT_INDEX, STATISTICS, METADATA, METADATA_INDEX, SUMMARY_OFFSET, DATA_END = 9, 10, 11, 12, 13, 14, 15
PARSERS: dict[int, Any] = {HEADER: Header, FOOTER: Footer, SCHEMA: Schema, CHANNEL: Channel, CHUNK: Chunk,
                           MESSAGE_INDEX: MessageIndex, CHUNK_INDEX: ChunkIndex, STATISTICS: Statistics,
                           METADATA: Metadata, METADATA_INDEX: MetadataIndex, SUMMARY_OFFSET: SummaryOffset,
                           DATA_END: DataEnd}
DATA_SECTION = {SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, ATTACHMENT, METADATA, DATA_END}
SUMMARY_SECTION = {SCHEMA, CHANNEL, CHUNK_INDEX, ATTACHMENT_INDEX, STATISTICS, METADATA_INDEX, SUMMARY_OFFSET, FOOTER}


def _parse(op: int, body: bytes) -> Any:
    """The record, parsed to exactly its length (ValueError otherwise)."""
    stream = io.BytesIO(body)
    record = (Message.read(ReadDataStream(stream), len(body)) if op == MESSAGE
              else PARSERS[op].read(ReadDataStream(stream)))
    if stream.tell() != len(body):
        raise ValueError(f"record {op:#04x} parses to {stream.tell()} of its {len(body)} bytes")
    return record


def _records(data: bytes, start: int, end: int) -> list[tuple[int, int, bytes]]:
    """(opcode, offset, body) of each record in data[start:end]; ValueError if the framing breaks."""
    out, pos = [], start
    while pos < end:
        if pos + 9 > end:
            raise ValueError(f"a record header cut off at {pos}")
        op, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], "little")
        if pos + 9 + length > end:
            raise ValueError(f"the record at {pos} (opcode {op:#04x}) runs {pos + 9 + length - end} bytes past its section")
        out.append((op, pos, data[pos + 9:pos + 9 + length]))
        pos += 9 + length
    return out


class Doctor:
    def __init__(self, data: bytes) -> None:
        self.data = data
        self.errors: list[str] = []
        self.schemas: dict[int, Schema] = {}  # in the data section
        self.channels: dict[int, Channel] = {}
        self.summary_schemas: set[int] = set()
        self.summary_channels: set[int] = set()
        self.chunks: dict[int, tuple[Chunk, int, set[int]]] = {}  # offset -> chunk, record length, channels in it
        self.chunk_indexes: dict[int, ChunkIndex] = {}
        self.counts: dict[int, int] = {}
        self.messages = 0
        self.min_time: int | None = None
        self.max_time: int | None = None
        self.statistics: Statistics | None = None
        self.metadata: dict[int, str] = {}  # offset -> name
        self.metadata_indexes: list[MetadataIndex] = []
        self.summary_offsets: list[SummaryOffset] = []

    def error(self, line: str) -> None:
        self.errors.append(line)

    def examine(self) -> list[str]:
        data = self.data
        if data[:8] != MAGIC or data[-8:] != MAGIC:
            return ["the file does not start and end with MCAP's magic"]
        try:
            records = _records(data, 8, len(data) - 8)
        except ValueError as exc:
            return [str(exc)]
        if not records or records[0][0] != HEADER:
            self.error("the first record is not the header")
        in_summary = False
        footer: Footer | None = None
        last_chunk: int | None = None
        message_indexes: dict[int, MessageIndex] = {}
        for k, (op, pos, body) in enumerate(records):
            try:
                record = _parse(op, body) if op in PARSERS or op == MESSAGE else None
            except Exception as exc:  # noqa: BLE001 - any parse failure is the finding
                self.error(f"the record at {pos} (opcode {op:#04x}) does not parse: {exc}")
                continue
            if op != MESSAGE_INDEX and last_chunk is not None:
                self._chunk(last_chunk, message_indexes)
                last_chunk, message_indexes = None, {}
            if k == 0:
                continue
            if op == HEADER:
                self.error(f"a second header at {pos}")
            elif op not in (DATA_SECTION | SUMMARY_SECTION):
                self.error(f"an unknown opcode {op:#04x} at {pos}")
            elif not in_summary and op not in DATA_SECTION:
                self.error(f"a {type(record).__name__} record in the data section at {pos}")
            elif in_summary and op not in SUMMARY_SECTION:
                self.error(f"a {type(record).__name__} record in the summary section at {pos}")
            if op == SCHEMA:
                self._schema(record, in_summary)
            elif op == CHANNEL:
                self._channel(record, in_summary)
            elif op == MESSAGE:
                self.error(f"a message outside every chunk at {pos} (this program writes chunked files)")
            elif op == CHUNK:
                self.chunks[pos] = (record, 9 + len(body), set())
                last_chunk = pos
            elif op == MESSAGE_INDEX:
                if last_chunk is None:
                    self.error(f"a message index at {pos} with no chunk before it")
                elif record.channel_id in message_indexes:
                    self.error(f"two message indexes for channel {record.channel_id} after the chunk at {last_chunk}")
                else:
                    message_indexes[record.channel_id] = record
            elif op == METADATA:
                self.metadata[pos] = record.name
            elif op == DATA_END:
                in_summary = True
            elif op == CHUNK_INDEX:
                if record.chunk_start_offset in self.chunk_indexes:
                    self.error(f"two chunk indexes for the chunk at {record.chunk_start_offset}")
                self.chunk_indexes[record.chunk_start_offset] = record
            elif op == STATISTICS:
                if self.statistics is not None:
                    self.error("more than one statistics record")
                self.statistics = record
            elif op == METADATA_INDEX:
                self.metadata_indexes.append(record)
            elif op == SUMMARY_OFFSET:
                self.summary_offsets.append(record)
            elif op == FOOTER:
                footer = record
                if pos != len(data) - 8 - 29:
                    self.error(f"the footer at {pos} is not the file's last record")
        if last_chunk is not None:
            self._chunk(last_chunk, message_indexes)
        if not in_summary:
            self.error("no data end record")
        if footer is None:
            self.error("no footer")
        else:
            self._summary(footer, records)
        return self.errors

    def _schema(self, s: Schema, in_summary: bool) -> None:
        if s.id == 0:
            self.error("a schema with the reserved id 0")
        if not s.encoding and s.data:
            self.error(f"schema {s.id} has no encoding but data")
        before = self.schemas.get(s.id)
        if before is not None and (before.name, before.encoding, before.data) != (s.name, s.encoding, s.data):
            self.error(f"two different schema records with id {s.id}")
        if in_summary:
            if before is None:
                self.error(f"schema {s.id} in the summary section does not exist in the data section")
            self.summary_schemas.add(s.id)
        else:
            self.schemas[s.id] = s

    def _channel(self, c: Channel, in_summary: bool) -> None:
        before = self.channels.get(c.id)
        if before is not None and ((before.topic, before.message_encoding, before.schema_id, before.metadata)
                                   != (c.topic, c.message_encoding, c.schema_id, c.metadata)):
            self.error(f"two different channel records with id {c.id}")
        if in_summary:
            if before is None:
                self.error(f"channel {c.id} in the summary section does not exist in the data section")
            self.summary_channels.add(c.id)
        else:
            self.channels[c.id] = c
        if c.schema_id and c.schema_id not in self.schemas:
            self.error(f"channel {c.id} with unknown schema {c.schema_id}")

    def _chunk(self, pos: int, message_indexes: dict[int, MessageIndex]) -> None:
        chunk, _, channels = self.chunks[pos]
        if chunk.compression == "zstd":
            try:
                contents = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
            except zstandard.ZstdError as exc:
                self.error(f"the chunk at {pos} does not decompress: {exc}")
                return
        elif chunk.compression == "":
            contents = bytes(chunk.data)
        else:
            self.error(f"the chunk at {pos} has compression {chunk.compression!r}, not one checked here")
            return
        if len(contents) != chunk.uncompressed_size:
            self.error(f"the chunk at {pos} holds {len(contents)} bytes, not its uncompressed_size {chunk.uncompressed_size}")
            return
        if chunk.uncompressed_crc and zlib.crc32(contents) != chunk.uncompressed_crc:
            self.error(f"the chunk at {pos}: its CRC does not match")
            return
        try:
            inner = _records(contents, 0, len(contents))
        except ValueError as exc:
            self.error(f"inside the chunk at {pos}: {exc}")
            return
        lo: int | None = None
        hi: int | None = None
        at_offset: dict[int, Message] = {}
        for op, off, body in inner:
            if op not in (SCHEMA, CHANNEL, MESSAGE):
                self.error(f"a record {op:#04x} inside the chunk at {pos} (only schemas, channels, messages)")
                continue
            try:
                record = _parse(op, body)
            except Exception as exc:  # noqa: BLE001
                self.error(f"inside the chunk at {pos}, the record at {off} does not parse: {exc}")
                continue
            if op == SCHEMA:
                self._schema(record, False)
            elif op == CHANNEL:
                self._channel(record, False)
            else:
                if record.channel_id not in self.channels:
                    self.error(f"a message on channel {record.channel_id} before its channel record (chunk at {pos})")
                channels.add(record.channel_id)
                at_offset[off] = record
                t = record.log_time
                lo, hi = (t if lo is None else min(lo, t)), (t if hi is None else max(hi, t))
                self.counts[record.channel_id] = self.counts.get(record.channel_id, 0) + 1
                self.messages += 1
        if lo is not None and hi is not None:
            if (lo, hi) != (chunk.message_start_time, chunk.message_end_time):
                self.error(f"the chunk at {pos} says its messages span {chunk.message_start_time}..{chunk.message_end_time},"
                           f" they span {lo}..{hi}")
            self.min_time = lo if self.min_time is None else min(self.min_time, lo)
            self.max_time = hi if self.max_time is None else max(self.max_time, hi)
        for cid, index in message_indexes.items():
            for t, off in index.records:
                m = at_offset.get(off)
                if m is None or m.channel_id != cid or m.log_time != t:
                    self.error(f"the message index for channel {cid} after the chunk at {pos} points at no such message"
                               f" (offset {off}, log time {t})")

    def _summary(self, footer: Footer, records: list[tuple[int, int, bytes]]) -> None:
        data = self.data
        footer_at = len(data) - 8 - 29
        if footer.summary_start:
            if footer.summary_crc:
                crc = zlib.crc32(struct.pack("<BQQQ", FOOTER, 20, footer.summary_start, footer.summary_offset_start),
                                 zlib.crc32(data[footer.summary_start:footer_at]))
                if crc != footer.summary_crc:
                    self.error("the footer's summary CRC does not match the summary")
            if data[footer.summary_start - 13] != DATA_END:
                self.error("the summary does not start right after the data end record")
        starts = {pos: op for op, pos, _ in records}
        for o in self.summary_offsets:
            if starts.get(o.group_start) != o.group_opcode:
                self.error(f"a summary offset for opcode {o.group_opcode:#04x} points at {o.group_start}, not at such a record")
        for m in self.metadata_indexes:
            if self.metadata.get(m.offset) != m.name:
                self.error(f"a metadata index for {m.name!r} points at {m.offset}, not at that metadata record")
        if self.chunk_indexes or self.summary_channels:
            for pos, (chunk, length, channels) in self.chunks.items():
                index = self.chunk_indexes.get(pos)
                if index is None:
                    self.error(f"the chunk at {pos} has no chunk index")
                    continue
                if (index.chunk_length, index.message_start_time, index.message_end_time, index.compression,
                        index.compressed_size, index.uncompressed_size) != (
                        length, chunk.message_start_time, chunk.message_end_time, chunk.compression, len(chunk.data),
                        chunk.uncompressed_size):
                    self.error(f"the chunk index for the chunk at {pos} does not match the chunk")
                for cid in channels:
                    if cid not in self.summary_channels:
                        self.error(f"the indexed chunk at {pos} has messages on channel {cid}, not in the summary")
                    elif self.channels[cid].schema_id and self.channels[cid].schema_id not in self.summary_schemas:
                        self.error(f"the indexed chunk at {pos} uses schema {self.channels[cid].schema_id}, not in the summary")
            for pos in self.chunk_indexes:
                if pos not in self.chunks:
                    self.error(f"a chunk index points at {pos}, where no chunk is")
        s = self.statistics
        if s is not None:
            if s.message_count != self.messages:
                self.error(f"statistics say {s.message_count} messages, the file holds {self.messages}")
            if self.messages and (s.message_start_time, s.message_end_time) != (self.min_time, self.max_time):
                self.error("statistics' message start and end times are not the messages'")
            for cid, n in self.counts.items():
                if s.channel_message_counts.get(cid, 0) != n:
                    self.error(f"statistics say {s.channel_message_counts.get(cid, 0)} messages on channel {cid},"
                               f" the file holds {n}")
            if s.chunk_count != len(self.chunks):
                self.error(f"statistics say {s.chunk_count} chunks, the file holds {len(self.chunks)}")


def doctor(path: Path) -> list[str]:
    """MCAP's checks on the file at ``path``: its errors, one line each (none: it passes)."""
    return Doctor(path.read_bytes()).examine()
