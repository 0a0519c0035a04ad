"""One walk over a recording's records, past damage (app.recording.reader's index is built here).

The MCAP framing is an opcode and a length per record. A chunk whose CRC, compression or
framing does not check out is skipped and the walk resyncs at the next chunk that does (found
by its framing if the damage hit a length field); a footer counts only where it must be; a
record that cannot stand where it is is damage like a bad chunk; a file cut off mid-chunk is
read up to its last complete chunk. What was skipped is kept as :class:`Damage`, for the
reader to say in ticks and seconds."""

from __future__ import annotations

from array import array
import io
import json
import re
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, BinaryIO

import numpy as np
import zstandard
from mcap.records import Channel, Chunk, Metadata, Schema, Statistics
from mcap.data_stream import ReadDataStream

from app.recording.schema import (CHANNELS_KEY, COUNTS_KEY, COUNTS_NAME, EVENT_TOPIC,
                                  IMAGE_TOPIC, METADATA_CRC_KEY, METADATA_NAME, PARAMS_TOPIC, TICK_TOPIC, TRIAL_TOPIC)

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_MESSAGE_INDEX, OP_STATISTICS, OP_METADATA, OP_DATA_END = 0x07, 0x0B, 0x0C, 0x0F
MAX_RECORD = 64 * 1024 * 1024  # no record this program writes comes near (chunks are ~256 KiB)
_TICK_HEAD = re.compile(rb'^\{"tick":(-?\d+),"t":')
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


@dataclass(frozen=True)
class Damage:
    """A stretch of the file that could not be read."""

    start_byte: int
    end_byte: int
    why: str  # "a damaged chunk", "cut off: an unfinished chunk", ...


def metadata_crc(record: dict[str, str]) -> str:
    """The CRC the writer puts in its metadata record (MCAP gives metadata none of its own)."""
    text = json.dumps({k: v for k, v in record.items() if k != METADATA_CRC_KEY}, sort_keys=True)
    return f"{zlib.crc32(text.encode('utf-8', 'surrogatepass')):08x}"


def metadata_checks_out(record: dict[str, str]) -> bool:
    """A copy whose CRC matches (older recordings carry none: taken as they are)."""
    return METADATA_CRC_KEY not in record or record[METADATA_CRC_KEY] == metadata_crc(record)


class _Unannounced(ValueError):
    """A chunk's message names a channel not announced so far."""


class _DamagedCopy(ValueError):
    """Our metadata record whose CRC does not match."""


def _chunk_contents(body: bytes) -> bytes:
    """A chunk record's body -> its uncompressed contents, CRC checked (ValueError if damaged)."""
    chunk = Chunk.read(ReadDataStream(io.BytesIO(body)))
    if chunk.compression == "zstd":
        contents = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    elif chunk.compression == "":
        contents = bytes(chunk.data)
    else:
        raise ValueError(f"compression {chunk.compression!r} is not one this program writes")
    if len(contents) != chunk.uncompressed_size:
        raise ValueError("chunk size does not match")
    if chunk.uncompressed_crc and zlib.crc32(contents) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC does not match")
    return contents


def _records(contents: bytes) -> Iterator[tuple[int, int, int]]:
    """(opcode, offset of the record, its length) for the records inside a chunk's contents."""
    pos, end = 0, len(contents)
    while pos + 9 <= end:
        op = contents[pos]
        length = int.from_bytes(contents[pos + 1:pos + 9], "little")
        if pos + 9 + length > end:
            raise ValueError("a record runs past the end of its chunk")
        yield op, pos, length
        pos += 9 + length
    if pos != end:
        raise ValueError("trailing bytes in a chunk")


class McapScan:
    """One walk over the file's records, building the index."""

    def __init__(self, f: BinaryIO, size: int) -> None:
        self.f, self.size = f, size
        self.topic_of: dict[int, str] = {}
        self.schema_name: dict[int, str] = {}
        self.channels: dict[str, str] = {}
        self.encoding: dict[str, str] = {}  # topic -> message encoding (json; protobuf for Foxglove's own)
        self.metadata: dict[str, str] = {}
        self.places: list[tuple[int, int]] = []
        # per tick and per frame: log time (ns), chunk number, offset in the chunk (compact: 24 bytes each)
        self.index: dict[str, tuple[array[int], array[int], array[int]]] = {
            topic: (array("q"), array("q"), array("q")) for topic in (TICK_TOPIC, IMAGE_TOPIC)}
        self.tick_numbers: array[int] = array("q")
        self.events: list[tuple[int, dict[str, Any]]] = []
        self.params: list[tuple[int, dict[str, Any]]] = []
        self.trials: list[dict[str, Any]] = []
        self.damage: list[Damage] = []
        self.complete = False
        self.good_bytes = 8
        self.later: list[tuple[int, int]] = []  # (offset, length) of chunks to read once the channels are known
        self.written: dict[int, int] = {}  # channel id -> messages written (a summary that checks out)
        self.data_end = size  # where the data section ends (the summary's start, when that checks out)
        self.trusted_summary: tuple[int, int] | None = None  # (start, footer offset) of a summary that checks out
        self.summary_damaged = False  # the file ends with its footer, but the summary's CRC fails
        self.counted: dict[int, int] | None = None  # the writer's counts record (after the last chunk), CRC checked
        self._resumed = 0

    def run(self) -> None:
        self._read_tail()
        self._walk()
        if self.trusted_summary is not None:
            self._read_summary(*self.trusted_summary)
        elif self.counted is not None:  # no summary to trust: the counts the writer wrote after its last chunk
            self.written = dict(self.counted)
        if not self.later:
            return
        # chunks whose channels were announced only in a damaged chunk: the summary section (a
        # finished file whose summary checks out) or the metadata's channel table named them by now
        for pos, length in self.later:
            self.f.seek(pos + 9)
            try:
                self._take_chunk(self.f.read(length))
            except Exception:  # noqa: BLE001 - still unknown, or damaged after all
                self.good_bytes -= 9 + length
                self.damage.append(Damage(pos, pos + 9 + length, "a chunk whose channels are not known"))
        self._in_time_order()

    def _in_time_order(self) -> None:
        """Chunks read out of order (above): every index in log-time order again."""
        for topic, (ns, chunks, offsets) in self.index.items():
            order = np.argsort(np.frombuffer(ns, dtype=np.int64), kind="stable")
            if len(order) and np.any(np.diff(order) != 1):
                if topic == TICK_TOPIC:
                    self.tick_numbers = array("q", np.frombuffer(self.tick_numbers, dtype=np.int64)[order].tolist())
                self.index[topic] = tuple(array("q", np.frombuffer(a, dtype=np.int64)[order].tolist())
                                          for a in (ns, chunks, offsets))  # type: ignore[assignment]
        self.events.sort(key=lambda e: e[0])
        self.params.sort(key=lambda e: e[0])

    def _read_tail(self) -> None:
        """The file's end, found where it must be (a footer of 20 bytes, then the magic, closing
        the file): ``complete`` if it is there; the summary trusted only if its CRC checks out.
        The data section then ends where the summary starts (``data_end``)."""
        footer_at = self.size - len(MAGIC) - 9 - 20
        if footer_at < 8:
            return
        self.f.seek(footer_at)
        tail = self.f.read(9 + 20 + len(MAGIC))
        if tail[0] != OP_FOOTER or int.from_bytes(tail[1:9], "little") != 20 or tail[29:] != MAGIC:
            return
        self.complete = True
        summary_start, _, crc = struct.unpack_from("<QQI", tail, 9)
        if not 8 < summary_start <= footer_at:
            self.summary_damaged = summary_start != 0  # 0: a file without a summary, as MCAP allows
            return
        if not self._summary_checks_out(footer_at, tail[9:29]):
            self.summary_damaged = True
            return
        self.trusted_summary = (summary_start, footer_at)
        self.data_end = summary_start
        self.f.seek(summary_start - 13)
        if self.f.read(9) == bytes([OP_DATA_END]) + (4).to_bytes(8, "little"):
            self.data_end = summary_start - 13  # the data end record: where the walk stops

    def _read_summary(self, start: int, end: int) -> None:
        """A summary section whose CRC checked out: its schemas, channels and message counts."""
        self.f.seek(start)
        data = self.f.read(end - start)
        pos = 0
        while pos + 9 <= len(data):
            op, length = data[pos], int.from_bytes(data[pos + 1:pos + 9], "little")
            body = data[pos + 9:pos + 9 + length]
            if op in (OP_SCHEMA, OP_CHANNEL, OP_STATISTICS):
                self._take(op, body)
            pos += 9 + length
        self.good_bytes += len(MAGIC) + 29 + (end - start) + (start - self.data_end)

    def _fits(self, op: int, pos: int, length: int, prev: int) -> bool:
        """The record can stand here in the data section of a file this program wrote: the
        header first; then metadata, chunks (each followed by any message indexes) and the data
        end record (4 bytes). A footer, a summary record or an opcode MCAP does not know cannot,
        and neither can a record that runs past the data section."""
        if length > MAX_RECORD or pos + 9 + length > self.data_end:
            return False
        if op == OP_HEADER:
            return pos == 8
        if op == OP_MESSAGE_INDEX:
            return prev in (OP_CHUNK, OP_MESSAGE_INDEX)
        if op == OP_DATA_END:
            return length == 4
        return op in (OP_METADATA, OP_CHUNK)

    def _walk(self) -> None:
        pos, prev = 8, 0
        limit = self.data_end
        while pos < limit:
            self.f.seek(pos)
            head = self.f.read(9)
            if len(head) < 9:
                self.damage.append(Damage(pos, self.size, "cut off: an unfinished record"))
                return
            op, length = head[0], int.from_bytes(head[1:9], "little")
            end = pos + 9 + length
            if not self._fits(op, pos, length, prev):
                if not self._skip_damage(pos, "a damaged stretch", op == OP_CHUNK and end > self.size):
                    return
                pos, prev = self._resumed, 0
                continue
            body = self.f.read(length)
            try:
                self._take(op, body)
            except _Unannounced:  # read again once the whole file said what its channels are
                self.later.append((pos, length))
                self.good_bytes += 9 + length
                pos, prev = end, op
                continue
            except _DamagedCopy:  # one copy of the metadata: the other (or the chunks) carry on
                self.damage.append(Damage(pos, end, "a damaged copy of the metadata"))
                pos, prev = end, op
                continue
            except Exception:  # noqa: BLE001 - damaged bytes raise assorted errors: skip to the next good chunk
                if not self._skip_damage(pos, "a damaged chunk" if op == OP_CHUNK else "a damaged record", False):
                    return
                pos, prev = self._resumed, 0
                continue
            if op == OP_DATA_END:
                if self.trusted_summary is None:  # the summary follows, unless a good chunk does: then this was no end
                    nxt = self._resync(end)
                    if nxt is not None:
                        self.damage.append(Damage(pos, nxt, "a damaged stretch"))
                        pos, prev = nxt, 0
                        continue
                    self.good_bytes += 9 + length
                    if self.summary_damaged:
                        self.damage.append(Damage(end, self.size, "a damaged summary"))
                    elif not self.complete:
                        self.damage.append(Damage(end, self.size, "cut off: in its summary"))
                    return
            self.good_bytes += 9 + length
            pos, prev = end, op

    def _skip_damage(self, pos: int, why: str, unfinished: bool) -> bool:
        """Damage from ``pos`` to the next chunk that checks out (``_resumed``); False when none
        follows: the damage runs to the end of the data (a cut-off file: to the file's end)."""
        nxt = self._resync(pos + 1)
        if nxt is not None:
            self.damage.append(Damage(pos, nxt, why))
            self._resumed = nxt
            return True
        if self.trusted_summary is not None:
            self.damage.append(Damage(pos, self.data_end, why))
        elif self.complete:
            self.damage.append(Damage(pos, self.size, "damaged to the end of its data, and its summary"
                                                      + (" is damaged" if self.summary_damaged else " is missing")))
        else:
            self.damage.append(Damage(pos, self.size, "cut off: an unfinished chunk" if unfinished
                                      else "cut off: damaged to the end"))
        return False

    def _summary_checks_out(self, footer_at: int, body: bytes) -> bool:
        """The summary section's CRC (in the footer) matches its bytes; a footer without one (0)
        cannot say, and is taken as it is."""
        summary_start, summary_offset_start, crc = struct.unpack_from("<QQI", body)
        if crc == 0:
            return True
        if not 0 < summary_start <= footer_at:
            return False
        self.f.seek(summary_start)
        summary = self.f.read(footer_at - summary_start)
        return bool(zlib.crc32(struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, summary_offset_start),
                               zlib.crc32(summary)) == crc)

    def _take(self, op: int, body: bytes) -> None:
        if op == OP_CHUNK:
            self._take_chunk(body)
        elif op == OP_METADATA:
            md = Metadata.read(ReadDataStream(io.BytesIO(body)))
            if md.name in (METADATA_NAME, COUNTS_NAME) and not metadata_checks_out(md.metadata):
                raise _DamagedCopy("a damaged copy of the metadata")
            if md.name == COUNTS_NAME and METADATA_CRC_KEY in md.metadata:  # the writer's counts, CRC checked
                self.counted = {int(c): int(n) for c, n in json.loads(md.metadata[COUNTS_KEY]).items()}
            if md.name not in (METADATA_NAME, COUNTS_NAME):  # this program writes no other: a damaged record
                raise ValueError("a metadata record this program does not write")
            if md.name == METADATA_NAME and not self.metadata:  # the first intact copy
                self.metadata = dict(md.metadata)
                self.metadata.pop(METADATA_CRC_KEY, None)
                self._channel_table(self.metadata.pop(CHANNELS_KEY, ""))
        elif op == OP_SCHEMA:
            self._schema(body)
        elif op == OP_CHANNEL:
            self._channel(body)
        elif op == OP_STATISTICS:  # the summary's count of messages per channel: the ticks written
            stats = Statistics.read(ReadDataStream(io.BytesIO(body)))
            self.written = dict(stats.channel_message_counts)
        elif op == OP_MESSAGE_INDEX:  # not written by this program; other writers put them after a chunk
            if len(body) < 6 or 6 + int.from_bytes(body[2:6], "little") != len(body):
                raise ValueError("a message index that does not add up")

    def _channel_table(self, text: str) -> None:
        """The channel table our writer puts in its metadata (schema.CHANNELS_KEY): what a damaged
        first chunk would otherwise take with it."""
        if not text:
            return
        for cid, (topic, encoding, schema) in json.loads(text).items():
            if int(cid) not in self.topic_of:
                self.topic_of[int(cid)] = str(topic)
                self.channels[str(topic)] = str(schema)
                self.encoding[str(topic)] = str(encoding)

    def _schema(self, body: bytes) -> None:
        s = Schema.read(ReadDataStream(io.BytesIO(body)))
        self.schema_name[s.id] = s.name

    def _channel(self, body: bytes) -> None:
        """A channel record; the first that named an id wins (a file never renames one, and the
        summary's copies, read last, have no CRC of their own)."""
        c = Channel.read(ReadDataStream(io.BytesIO(body)))
        if c.id in self.topic_of:
            return
        self.topic_of[c.id] = c.topic
        self.channels[c.topic] = self.schema_name.get(c.schema_id, "")
        self.encoding[c.topic] = c.message_encoding

    def _take_chunk(self, body: bytes) -> None:
        contents = _chunk_contents(body)
        found: list[tuple[str, int, int, bytes]] = []  # checked whole before any of it is kept
        for op, off, length in _records(contents):
            if op == OP_SCHEMA:
                self._schema(contents[off + 9:off + 9 + length])
            elif op == OP_CHANNEL:
                self._channel(contents[off + 9:off + 9 + length])
            elif op == OP_MESSAGE:
                channel, _, log_time, _ = _MESSAGE_HEAD.unpack_from(contents, off + 9)
                topic = self.topic_of.get(channel)
                if topic is None:  # announced in a chunk that was damaged: the summary may say it
                    raise _Unannounced("a message on a channel not announced (yet)")
                start = off + 9 + _MESSAGE_HEAD.size
                head = contents[start:start + 40] if topic == TICK_TOPIC else contents[start:off + 9 + length]
                found.append((topic, log_time, off, head))
        chunk = len(self.places)
        for topic, _, _, head in found:  # the counters first: a chunk is taken whole or not at all
            if topic == TICK_TOPIC:
                m = _TICK_HEAD.match(head)
                if m is None:
                    raise ValueError("a tick message without its counter")
        for topic, log_time, off, head in found:
            if topic == TICK_TOPIC:
                self.tick_numbers.append(int(_TICK_HEAD.match(head).group(1)))  # type: ignore[union-attr]  # checked above
            if topic in self.index:
                ns, chunks, offsets = self.index[topic]
                ns.append(log_time)
                chunks.append(chunk)
                offsets.append(off)
            elif topic == EVENT_TOPIC:
                self.events.append((log_time, json.loads(head)))
            elif topic == PARAMS_TOPIC:
                self.params.append((log_time, json.loads(head)))
            elif topic == TRIAL_TOPIC:
                self.trials.append(json.loads(head))
        self.places.append((self.f.tell() - len(body) - 9, len(body)))

    def _resync(self, start: int) -> int | None:
        """The offset of the next chunk record (or metadata record of ours) at or after ``start``
        (within the data section) whose framing and CRC check out."""
        block = 1 << 20
        pos = start
        while pos < self.data_end:
            self.f.seek(pos)
            data = self.f.read(block + 9)
            k = _next_candidate(data, 0)
            while k != -1 and k < block:
                cand = pos + k
                if k + 9 <= len(data):
                    length = int.from_bytes(data[k + 1:k + 9], "little")
                    if 32 <= length <= MAX_RECORD and cand + 9 + length <= self.data_end:
                        self.f.seek(cand + 9)
                        try:
                            body = self.f.read(length)
                            if data[k] == OP_CHUNK:
                                _chunk_contents(body)
                                return cand
                            md = Metadata.read(ReadDataStream(io.BytesIO(body)))
                            if (md.name in (METADATA_NAME, COUNTS_NAME) and METADATA_CRC_KEY in md.metadata
                                    and metadata_checks_out(md.metadata)):
                                return cand
                        except Exception:  # noqa: BLE001 - not a record after all
                            pass
                k = _next_candidate(data, k + 1)
            pos += block
        return None


def _next_candidate(data: bytes, start: int) -> int:
    """Where the next chunk or metadata opcode is in ``data`` from ``start`` (-1: none)."""
    hits = [k for k in (data.find(bytes([OP_CHUNK]), start), data.find(bytes([OP_METADATA]), start)) if k != -1]
    return min(hits) if hits else -1
