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
of its own); a damaged summary is said, and its counts are not used. The walk itself (the
damage scan and the resync) is app.recording.scan's.
"""

from __future__ import annotations

import bisect
import io
import json
import os
import struct
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, overload

import numpy as np
from mcap.records import Metadata
from mcap.data_stream import ReadDataStream

from app.params import Params
from app.recording.scan import (MAGIC, MAX_RECORD, OP_CHUNK, OP_HEADER, OP_METADATA, _MESSAGE_HEAD, Damage, McapScan,
                                _chunk_contents, metadata_checks_out, metadata_crc)
from app.recording.schema import CHUNK_BYTES, CHUNK_SECONDS, IMAGE_TOPIC, METADATA_NAME, TICK_TOPIC

CHUNKS_KEPT = 4  # decoded chunks kept for the sequences (a few MB)
# the walk over the records (past damage) is app.recording.scan's; its names are read from here too
__all__ = ["MAGIC", "Damage", "Gap", "McapScan", "Recording", "RecordingError", "check_ticks", "is_session", "metadata_checks_out", "metadata_crc", "params_from_payload",
           "params_from_recording", "params_index", "read_recording", "session_clock", "session_record"]


class RecordingError(ValueError):
    """A file that is not a readable recording: one line for people."""


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
        scan = McapScan(f, size)
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
    from app.params import PARAMETERS, ParamsStore

    store = ParamsStore()
    if not isinstance(d, dict):  # a damaged record: the defaults
        return store.get()
    recorded = [row for row in PARAMETERS.values() if row.recorded]  # the parameter table's (core.bounds)
    changes = {row.name: d[row.name] for row in recorded if row.kind != "gain" and row.name in d}
    gains = d.get("gains")
    gain_names = {row.name for row in recorded if row.kind == "gain"}
    changes.update({k: v for k, v in gains.items() if k in gain_names} if isinstance(gains, dict) else {})
    for key, value in changes.items():  # one at a time: a spoiled field is skipped, not the whole set
        try:
            store.update("recording", **{key: value})
        except (ValueError, TypeError):
            continue
    return store.get()
