"""Reading a recording back: in bounded memory, past damage, saying exactly what was lost.

Opening a recording walks its records once (the MCAP framing: an opcode and a length per
record) and keeps an index, not the messages: per tick and per camera frame its time and
where it sits (which chunk, which offset inside it). ``Recording.ticks`` and
``Recording.frames`` are sequences that decode a chunk when one of its messages is asked
for (the last few decoded chunks are kept), so ``report`` and ``replay`` hold a few chunks
and the index whatever the file's length, and a seek anywhere costs one chunk.

Every chunk carries a CRC of its contents. A chunk whose CRC, compression or framing does
not check out is skipped, and reading goes on at the next chunk that does (found by its
framing if the damage hit a length field). No damaged record ends the reading: a footer
counts only where it must be (20 bytes, then the magic that closes the file), and a record
that cannot stand where it is (a footer or summary record in the data section, an opcode
MCAP does not know, a length past the data section) is damage like a bad chunk. A file cut
off mid-chunk (a killed writer, power loss) is read up to its last complete chunk. What
could not be read is said in ticks and seconds: the tick counter of the loop runs without
gaps, so a gap is a loss. How many ticks were written comes only from a record whose CRC
checks out: the summary, or else the writer's count after its last chunk (a metadata record
of its own); a damaged summary is said, and its counts are not used.
"""

from __future__ import annotations

import bisect
from array import array
import io
import json
import os
import re
import struct
import zlib
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, overload

import numpy as np
import zstandard
from mcap.records import Channel, Chunk, Metadata, Schema, Statistics
from mcap.data_stream import ReadDataStream

from app.params import Params
from app.recording.schema import (CHANNELS_KEY, CHUNK_BYTES, CHUNK_SECONDS, COUNTS_KEY, COUNTS_NAME, EVENT_TOPIC,
                                  IMAGE_TOPIC,
                                  METADATA_CRC_KEY, METADATA_NAME, PARAMS_TOPIC,
                                  TICK_TOPIC, TRIAL_TOPIC)

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_MESSAGE_INDEX, OP_STATISTICS, OP_METADATA, OP_DATA_END = 0x07, 0x0B, 0x0C, 0x0F
MAX_RECORD = 64 * 1024 * 1024  # no record this program writes comes near (chunks are ~256 KiB)
CHUNKS_KEPT = 4  # decoded chunks kept for the sequences (a few MB)
_TICK_HEAD = re.compile(rb'^\{"tick":(-?\d+),"t":')
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time


class RecordingError(ValueError):
    """A file that is not a readable recording: one line for people."""


@dataclass(frozen=True)
class Damage:
    """A stretch of the file that could not be read."""

    start_byte: int
    end_byte: int
    why: str  # "a damaged chunk", "cut off: an unfinished chunk", ...


@dataclass(frozen=True)
class Gap:
    """Ticks missing between two that were read (by the loop's tick counter): after tick
    ``after_tick`` (-1: from the session's start) and before ``before_tick``; ``t_from`` and
    ``t_to`` are the session times of the ticks either side (where the loss is)."""

    after_tick: int
    before_tick: int
    t_from: float
    t_to: float
    dt: float = 0.0  # the session's tick interval (s)

    @property
    def ticks(self) -> int:
        return self.before_tick - self.after_tick - 1

    @property
    def seconds(self) -> float:
        """The session time the missing ticks stood for."""
        return self.ticks * self.dt if self.dt > 0 else self.t_to - self.t_from


class _Chunks:
    """Decoded chunks by number, the last few kept: (topic, log time ns, payload bytes) per message."""

    def __init__(self, path: Path, places: list[tuple[int, int]], topic_of: dict[int, str]) -> None:
        self.path = path
        self.places = places  # per chunk: (offset of its record, record length)
        self.topic_of = topic_of
        self._kept: OrderedDict[int, list[bytes]] = OrderedDict()
        self._file: BinaryIO | None = None

    def message(self, chunk: int, offset: int) -> bytes:
        """The payload of the message at ``offset`` in chunk ``chunk``'s contents."""
        data = self._kept.get(chunk)
        if data is None:
            data = self._decode(chunk)
        else:
            self._kept.move_to_end(chunk)
        contents = data[0]
        length = int.from_bytes(contents[offset + 1:offset + 9], "little")
        start = offset + 9 + _MESSAGE_HEAD.size
        return contents[start:offset + 9 + length]

    def _decode(self, chunk: int) -> list[bytes]:
        if self._file is None:
            self._file = open(self.path, "rb")  # noqa: SIM115 - kept open for the life of the recording
        pos, length = self.places[chunk]
        self._file.seek(pos + 9)
        body = self._file.read(length)
        contents = _chunk_contents(body)
        self._kept[chunk] = [contents]
        while len(self._kept) > CHUNKS_KEPT:
            self._kept.popitem(last=False)
        return self._kept[chunk]

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


class _Messages(Sequence[Any]):
    """Messages of one topic, decoded on demand from their chunks."""

    def __init__(self, chunks: _Chunks, where: np.ndarray, decode: Any) -> None:
        self._chunks = chunks
        self._where = where  # (n, 2) chunk number, offset in the chunk's contents
        self._decode = decode

    def __len__(self) -> int:
        return int(self._where.shape[0])

    @overload
    def __getitem__(self, k: int) -> Any: ...

    @overload
    def __getitem__(self, k: slice) -> list[Any]: ...

    def __getitem__(self, k: int | slice) -> Any:
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        if k < 0:
            k += len(self)
        if not 0 <= k < len(self):
            raise IndexError(k)
        chunk, offset = self._where[k]
        return self._decode(k, self._chunks.message(int(chunk), int(offset)))

    def __iter__(self) -> Iterator[Any]:
        for k in range(len(self)):
            yield self[k]

    def __eq__(self, other: object) -> bool:  # compares as the list it stands for
        if isinstance(other, (list, tuple, _Messages)):
            return len(self) == len(other) and all(a == b for a, b in zip(self, other))
        return NotImplemented

    __hash__ = None  # type: ignore[assignment]  # a mutable-looking sequence, like list


@dataclass
class Recording:
    """A recording's metadata, channels, events and parameter changes, and its ticks and frames
    as sequences that read from the file when asked (see the module docstring)."""

    path: Path
    metadata: dict[str, str]
    channels: dict[str, str]  # topic -> schema name
    complete: bool  # the file ends with its footer (its writer finished it)
    bytes_total: int
    bytes_read: int  # bytes that were read as good records
    damage: list[Damage]
    t: np.ndarray  # (ticks,) session time of each tick (s)
    tick_numbers: np.ndarray  # (ticks,) the loop's tick counter
    frame_t: np.ndarray  # (frames,) session time of each camera frame (s)
    events: list[dict[str, Any]]
    params: list[tuple[float, dict[str, Any]]]  # (t, the full parameter set) at start and on change
    trials: list[dict[str, Any]] = field(default_factory=list)  # the step tests (app.live.tuning.Trial.payload)
    ticks_written: int | None = None  # what the file's summary says it holds (None: no summary that checks out)
    frames_written: int | None = None  # likewise for camera frames
    summary_damaged: bool = False  # finished, but its summary's CRC fails: its counts are not used
    ticks: Sequence[dict[str, Any]] = field(repr=False, default=())
    frames: Sequence[tuple[float, bytes]] = field(repr=False, default=())  # (t, JPEG)
    _chunks: _Chunks | None = field(repr=False, default=None)

    def gaps(self) -> list[Gap]:
        """Where the tick counter jumps: ticks that are not in the file. A session's recording
        starts at tick 0 (app.recording.writer), so a first readable tick above 0 means the ticks
        before it were lost (a damaged first chunk): a gap from the session's start."""
        k = self.tick_numbers
        if len(k) == 0:
            return []
        dt = self.tick_dt()
        lead = [Gap(-1, int(k[0]), 0.0, float(self.t[0]), dt)] if k[0] > 0 else []
        jumps = np.nonzero(np.diff(k) > 1)[0]
        inner = [Gap(int(k[i]), int(k[i + 1]), float(self.t[i]), float(self.t[i + 1]), dt) for i in jumps]
        tail = []
        if self.ticks_written is not None:  # a finished file says how many ticks it holds: the rest is lost
            missing = self.ticks_written - len(k) - sum(g.ticks for g in lead + inner)
            if missing > 0:
                tail = [Gap(int(k[-1]), int(k[-1]) + missing + 1, float(self.t[-1]), float(self.t[-1]) + (missing + 1) * dt,
                            dt)]
        return lead + inner + tail

    def tick_dt(self) -> float:
        """The loop's tick interval, from the ticks read (s)."""
        steps = np.diff(self.t) / np.maximum(np.diff(self.tick_numbers), 1) if len(self.t) > 1 else np.zeros(0)
        return float(np.median(steps)) if len(steps) else 0.0

    @property
    def lost_ticks(self) -> int:
        return sum(g.ticks for g in self.gaps())

    @property
    def lost_s(self) -> float:
        return float(sum(g.seconds for g in self.gaps()))

    def loss_note(self) -> str:
        """What could not be read, in ticks and seconds; '' for a whole, undamaged file."""
        parts = []
        for g in self.gaps():
            parts.append(f"{g.ticks} ticks ({g.seconds:.2f} s, t = {g.t_from:.2f}–{g.t_to:.2f} s) missing")
        if parts and self.ticks_written is not None:
            parts.insert(0, f"{self.ticks_written} ticks written, {len(self.t)} read, {self.lost_ticks} lost"
                            f" ({self.lost_s:.2f} s)")
        if self.frames_written is not None and self.frames_written > len(self.frame_t):
            parts.append(f"{self.frames_written - len(self.frame_t)} of {self.frames_written} camera frames missing"
                         " (no tick)")
        damaged = [d for d in self.damage if not d.why.startswith("cut off")]
        if damaged:
            size = sum(d.end_byte - d.start_byte for d in damaged)
            parts.append(f"{len(damaged)} damaged stretch{'es' if len(damaged) > 1 else ''} of the file"
                         f" ({size / 1024:.0f} KiB) skipped")
        if self.summary_damaged and self.ticks_written is None:
            last = float(self.t[-1]) if len(self.t) else 0.0
            parts.append(f"its summary is damaged (its CRC fails) and so is the writer's count after its last chunk,"
                         f" so how many ticks were written is not known: a loss after the last tick read"
                         f" (t = {last:.2f} s) cannot be counted")
        elif self.summary_damaged:
            parts.append("its summary is damaged (its CRC fails): the ticks written are the writer's count after its"
                         " last chunk")
        if not self.complete:
            last = float(self.t[-1]) if len(self.t) else 0.0
            tail = self.bytes_total - max((d.start_byte for d in self.damage if d.why.startswith("cut off")),
                                          default=self.bytes_total)
            unread = (f" the last {tail} bytes (an unfinished chunk: at most {CHUNK_SECONDS:g} s or"
                      f" {CHUNK_BYTES // 1024} KiB of messages) could not be read, and" if tail else
                      f" it ends after a whole chunk (the writer's unfinished one, at most {CHUNK_SECONDS:g} s, never"
                      " reached it), and")
            parts.append(f"the file was cut off (no summary): recovered {len(self.t)} ticks up to t = {last:.2f} s;"
                         f"{unread} what the session did after that is not in the file")
        return f"{self.path.name}: " + "; ".join(parts) if parts else ""

    def close(self) -> None:
        if self._chunks is not None:
            self._chunks.close()


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


class _Scan:
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


def session_record(path: Path) -> dict[str, str] | None:
    """The metadata record of a session this program recorded (an MCAP file whose header names
    omniformation as its writer and whose first records include our metadata record, which
    app.recording.writer writes before the first chunk); None for any other file. The first
    copy whose CRC checks out; a file whose copies both fail is not taken for a session."""
    try:
        with open(path, "rb") as f:
            if f.read(8) != MAGIC:
                return None
            for k in range(8):  # the header, then our metadata (twice) before any chunk
                head = f.read(9)
                if len(head) < 9:
                    return None
                op, length = head[0], int.from_bytes(head[1:9], "little")
                if length > MAX_RECORD or op == OP_CHUNK:
                    return None
                body = f.read(length)
                if k == 0:
                    if op != OP_HEADER:
                        return None
                    profile_len = int.from_bytes(body[:4], "little")
                    library = body[8 + profile_len:8 + profile_len + int.from_bytes(body[4 + profile_len:8 + profile_len],
                                                                                  "little")]
                    if library != b"omniformation":
                        return None
                elif op == OP_METADATA:
                    md = Metadata.read(ReadDataStream(io.BytesIO(body)))
                    if md.name != METADATA_NAME:
                        return None
                    if metadata_checks_out(md.metadata):
                        return dict(md.metadata)
    except (OSError, ValueError, struct.error, UnicodeDecodeError):
        return None
    return None


def _next_candidate(data: bytes, start: int) -> int:
    """Where the next chunk or metadata opcode is in ``data`` from ``start`` (-1: none)."""
    hits = [k for k in (data.find(bytes([OP_CHUNK]), start), data.find(bytes([OP_METADATA]), start)) if k != -1]
    return min(hits) if hits else -1


def is_session(path: Path) -> bool:
    """The file is a session this program recorded (see :func:`session_record`). Retention
    deletes nothing else."""
    return session_record(path) is not None


def read_recording(path: Path) -> Recording:
    """Open a recording (see the module docstring). A file that is not an omniformation
    recording, or holds no readable tick, raises :class:`RecordingError` (one line)."""
    if not path.is_file():
        raise RecordingError(f"{path}: no such recording")
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        head = f.read(8)
        if len(head) < 8 or sum(a != b for a, b in zip(head, MAGIC)) > 2:  # a damaged byte or two is still ours
            raise RecordingError(f"{path.name}: not an MCAP file")
        scan = _Scan(f, size)
        scan.run()
    if TICK_TOPIC not in scan.channels and not scan.damage:
        raise RecordingError(f"{path.name}: an MCAP file, but not an omniformation recording (no {TICK_TOPIC})")
    if not scan.index[TICK_TOPIC][0]:
        raise RecordingError(f"{path.name}: the recording holds no complete tick (cut off or damaged in its first chunk)")
    try:
        start_ns = int(scan.metadata.get("start_ns", "0") or 0)
    except ValueError:
        raise RecordingError(f"{path.name}: its metadata start_ns is not a number") from None
    chunks = _Chunks(path, scan.places, scan.topic_of)

    def where(topic: str) -> tuple[np.ndarray, np.ndarray]:
        ns, chunk, offset = (np.frombuffer(a, dtype=np.int64) if len(a) else np.zeros(0, np.int64)
                             for a in scan.index[topic])
        return (ns - start_ns) / 1e9, np.column_stack([chunk, offset])

    tick_t, ticks_at = where(TICK_TOPIC)
    frame_t, frames_at = where(IMAGE_TOPIC)
    tick_t, frame_t = session_clock(tick_t), session_clock(frame_t)

    def tick(_: int, data: bytes) -> dict[str, Any]:
        return dict(json.loads(data))

    protobuf_frames = scan.encoding.get(IMAGE_TOPIC) == "protobuf"

    def frame(k: int, data: bytes) -> tuple[float, bytes]:
        if protobuf_frames:  # Foxglove's CompressedImage (recordings since the published schemas)
            from app.recording.foxglove import decode_image

            return float(frame_t[k]), decode_image(data)
        import base64  # older recordings: JSON with the JPEG in base64

        return float(frame_t[k]), base64.b64decode(json.loads(data)["data"])

    params = []
    tick_ns = scan.index[TICK_TOPIC][0]
    for ns, p in scan.params:
        before = bisect.bisect_right(tick_ns, ns) - 1
        params.append((float(tick_t[before]) if before >= 0 else 0.0, p))
    return Recording(
        path=path, metadata=scan.metadata, channels=scan.channels, complete=scan.complete,
        bytes_total=size, bytes_read=scan.good_bytes, damage=scan.damage, t=tick_t,
        tick_numbers=np.frombuffer(scan.tick_numbers, dtype=np.int64) if len(scan.tick_numbers) else np.zeros(0, np.int64),
        frame_t=frame_t,
        events=[e for _, e in scan.events], params=params, trials=scan.trials,
        ticks_written=next((n for cid, n in scan.written.items() if scan.topic_of.get(cid) == TICK_TOPIC), None),
        frames_written=next((n for cid, n in scan.written.items() if scan.topic_of.get(cid) == IMAGE_TOPIC),
                            None if not scan.written else 0),
        summary_damaged=scan.summary_damaged,
        ticks=_Messages(chunks, ticks_at, tick), frames=_Messages(chunks, frames_at, frame), _chunks=chunks,
    )


def check_ticks(rec: Recording) -> None:
    """RecordingError (one line) unless the first and last ticks are what the loop records."""
    from app.recording.schema import tick_from_payload

    for k in (0, len(rec.ticks) - 1):
        try:
            tick_from_payload(rec.ticks[k])
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise RecordingError(f"{rec.path.name}: tick {k} is not what omniformation records"
                                 f" ({type(exc).__name__}: {exc})"[:300]) from None


def session_clock(t: np.ndarray) -> np.ndarray:
    """Times in file order that never go back. Recordings made before the writer kept the
    session's clock (app.recording.writer) set their time back to 0 at a reset; each such step
    back is taken as one tick after the time before it (the median step), so a timeline reaches
    every part of the session. Times that never go back are returned as they are."""
    back = np.flatnonzero(np.diff(t) < -1e-9)
    if not len(back):
        return t
    steps = np.diff(t)
    step = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 0.0
    out = np.array(t, dtype=np.float64)
    for i in back:  # in order: each shift carries the ones before it
        out[i + 1:] += out[i] + step - out[i + 1]
    return out


def params_index(times: list[float], t: float) -> int:
    """Which of the recorded parameter sets (coming in force at ``times``, in order) is in force
    at session time ``t``: the last at or before it (the first one before any)."""
    return max(0, bisect.bisect_right(times, t + 1e-9) - 1)


def params_from_recording(rec: Recording, t: float | None = None) -> Params:
    """The parameter set in force at session time ``t`` (None: when the recording started)."""
    if not rec.params:
        return Params()
    k = 0 if t is None else params_index([at for at, _ in rec.params], t)
    return params_from_payload(rec.params[k][1])


def params_from_payload(d: dict[str, Any]) -> Params:
    """A recorded parameter set as ``Params``: what the file holds, within today's bounds (a value
    an older version allowed is clamped, as the page would; a missing or damaged field keeps
    its default)."""
    from app.params import ParamsStore
    from core.types import GAIN_BOUNDS

    store = ParamsStore()
    if not isinstance(d, dict):  # a damaged record: the defaults
        return store.get()
    keys = ("leader_mode", "leader_speed_mps", "leader_turn_deg_s", "slots", "n_followers", "safety",
            "safety_distance_m", "goal", "min_scale", "stop", "paused")
    changes = {key: d[key] for key in keys if key in d}
    gains = d.get("gains")
    changes.update({k: v for k, v in gains.items() if k in GAIN_BOUNDS} if isinstance(gains, dict) else {})
    for key, value in changes.items():  # one at a time: a spoiled field is skipped, not the whole set
        try:
            store.update("recording", **{key: value})
        except (ValueError, TypeError):
            continue
    return store.get()
