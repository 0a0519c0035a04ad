"""Writing a session to MCAP (channels and payloads: app.recording.schema).

Messages are queued and written by one writer thread, so the loop never waits on the disk.
Crash safety: messages are written in zstd chunks that close at the first of ``CHUNK_BYTES``
and ``CHUNK_SECONDS`` of session, camera frames in chunks apart from the ticks, every chunk
readable on its own and handed to the operating system as it closes
(app.recording.mcap_out); SIGINT / SIGTERM finish the file (summary and index). A file cut
off by SIGKILL or power loss is read up to its last complete chunk: all but about its last
second (app.recording.reader).

A disk is allowed to fail. A write error (a full disk, a pulled USB stick) or free space
below the floor stops the recording cleanly: what was written stays readable, the reason is
kept in :attr:`Recorder.failure` and handed to ``on_stopped`` (the page and the log say it),
and the loop and the robots carry on. Closing never waits longer than ``CLOSE_TIMEOUT_S`` on
the disk. :func:`apply_retention` keeps a recordings folder within its budget.

A session being written is locked: the recorder holds an exclusive ``flock`` on its file from
the moment it creates it until the file is finished (closed), and other processes see it.
Retention tries the same lock without waiting and never deletes a file it cannot take, so
two services on one recordings folder never delete each other's live session. Retention
deletes only the live service's sessions (metadata ``retention = "service"``, set by
app.services.recording); what ``simulate --record``, ``rerun``, ``bench`` or an export
write is never the service's to delete.
"""

from __future__ import annotations

import fcntl
import json
import logging
import math
import queue
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from app.params import Params, params_events
from core.types import Image
from app.tick import SessionClock, TickState
from app.recording.foxglove import PROTOBUF_TOPICS, encode, schema_data
from app.recording.mcap_out import SessionWriter
from app.recording.reader import metadata_crc
from app.recording.schema import (CHANNELS_KEY, CHUNK_BYTES, CHUNK_SECONDS, COUNTS_KEY, COUNTS_NAME, EVENT_TOPIC,
                                  IMAGE_TOPIC,
                                  METADATA_COPIES, METADATA_CRC_KEY, METADATA_NAME, PARAMS_TOPIC, SCAN_HZ, SCAN_TOPIC,
                                  SCHEMAS, TF_TOPIC, TICK_TOPIC, TOPIC_SCHEMA, TRIAL_TOPIC, image_payload, jsonable,
                                  params_payload, scan_payload, tick_payload, transforms_payload)

DEFAULT_FRAME_RATE_HZ = 10.0
MAX_FRAMES_WAITING = 30  # raw frames queued for JPEG encoding on the writer thread (3 s at 10 Hz)
DEFAULT_FREE_FLOOR_BYTES = 200 * 1024 * 1024  # a recording stops before the disk is this full
CLOSE_TIMEOUT_S = 10.0  # closing waits at most this long for a slow disk

log = logging.getLogger(__name__)


class RecordingRefused(OSError):
    """A recording that cannot start (no room, no folder): one line for people."""


def channel_table(channels: dict[str, int]) -> str:
    """The channel ids a recording uses, as JSON: {"id": [topic, message encoding, schema name]}."""
    table = {str(cid): [topic, "protobuf" if topic in PROTOBUF_TOPICS else "json", TOPIC_SCHEMA[topic]]
             for topic, cid in channels.items()}
    return json.dumps(table, separators=(",", ":"))


def free_bytes(folder: Path) -> int:
    return shutil.disk_usage(folder).free


def check_room(target: Path, floor_bytes: int) -> None:
    """RecordingRefused when the disk that holds ``target`` (a recording's file, or the folder it will
    be made in: its nearest existing folder is measured) has less than ``floor_bytes`` free. `run`
    asks before it starts anything; the recorder asks again as it opens its file."""
    probe = target if target.is_dir() else target.parent
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    free = free_bytes(probe)
    if free < floor_bytes:
        raise RecordingRefused(f"{target}: only {free / 1e6:.0f} MB free on its disk, below the floor of"
                               f" {floor_bytes / 1e6:.0f} MB; free some space or record elsewhere")


RETENTION_KEY = "retention"  # metadata: "service" on the live service's sessions, the only ones retention deletes
RETENTION_SERVICE = "service"


def _services_session(path: Path) -> bool:
    """A session the live service recorded: its metadata says so (older recordings, made before
    the mark: their command was ``omniformation run``)."""
    from app.recording.reader import session_record

    meta = session_record(path)
    if meta is None:
        return False
    if RETENTION_KEY in meta:
        return meta[RETENTION_KEY] == RETENTION_SERVICE
    return meta.get("command", "").split(" ")[:2] == ["omniformation", "run"]


def _delete_unless_locked(path: Path) -> bool:
    """Delete ``path`` while holding its lock; False (left alone) if a recorder holds the lock."""
    try:
        with open(path, "rb") as f:
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return False  # being written
            path.unlink()
            return True
    except FileNotFoundError:
        return False


def apply_retention(folder: Path, max_total_bytes: int, keep: tuple[Path, ...] = ()) -> list[Path]:
    """Delete the oldest of the live service's sessions directly in ``folder`` (never its
    sub-folders: samples/ is kept) until the sessions there add up to at most
    ``max_total_bytes``; the paths deleted. A session is a file this program recorded, known by
    its header and metadata (app.recording.reader.session_record), never by its name: other
    files are never touched. A session being written (locked: see the module docstring) counts
    towards the total and is never deleted; neither is one another command wrote."""
    from app.recording.reader import is_session

    if not folder.is_dir():
        return []
    keep_resolved = {p.resolve() for p in keep}
    sessions = sorted((p for p in folder.iterdir() if p.is_file() and not p.is_symlink() and is_session(p)),
                      key=lambda p: p.stat().st_mtime)
    total = sum(p.stat().st_size for p in sessions)
    deleted = []
    for p in sessions:
        if total <= max_total_bytes:
            break
        if p.resolve() in keep_resolved or not _services_session(p):
            continue
        size = p.stat().st_size
        if _delete_unless_locked(p):
            total -= size
            deleted.append(p)
    return deleted


NOTICEABLE_MPS = 0.005  # a change the event's two decimals show (0.01 m/s); less is no change for people


def _safety_kind(text: str, changed: Any = None) -> str:
    """"off", "inactive", "changed", "infeasible" or "no solver": an event when it changes, not every
    tick. A "changed" under NOTICEABLE_MPS for everyone counts as "inactive": no event that says
    "changed F1 0.00 m/s"."""
    rest = text.partition(", ")[2]
    kind = rest.split(":")[0].split(" F")[0] if rest else text
    if kind.startswith("changed") and (changed is None or not np.any(np.abs(np.asarray(changed, float)) >= NOTICEABLE_MPS)):
        return "inactive"
    return kind


def tick_events(prev: TickState | None, s: TickState) -> list[tuple[str, str]]:
    """Events a tick shows compared with the one before: lost / found, link, phase, STOP."""
    ev: list[tuple[str, str]] = []
    if prev is None or prev.n != s.n:
        return ev
    for i in range(s.n):
        if bool(prev.tracked[i]) and not bool(s.tracked[i]):
            ev.append(("lost", f"follower {i + 1} lost"))
        elif not bool(prev.tracked[i]) and bool(s.tracked[i]):
            ev.append(("found", f"follower {i + 1} found"))
    if prev.link_state != s.link_state:
        ev.append(("link", f"link {prev.link_state} -> {s.link_state}"))
    if _safety_kind(prev.safety, prev.safety_changed) != _safety_kind(s.safety, s.safety_changed) and s.safety:
        ev.append(("safety", f"safety filter {s.safety}"))
    if prev.phase != s.phase:
        ev.append(("phase", f"vision {prev.phase} -> {s.phase}"))
    if prev.stopped != s.stopped:
        ev.append(("stop", "STOP: every follower at zero" if s.stopped else "STOP released"))
    return ev


class Recorder:
    """Writes a session: subscribe ``on_tick`` to the loop and ``on_params`` to the store.

    Messages are queued and written by one writer thread, so the loop never waits on the disk.
    """

    def __init__(self, path: Path, metadata: dict[str, str], params: Params,
                 frame_rate_hz: float = DEFAULT_FRAME_RATE_HZ, jpeg_quality: int = 80,
                 start_ns: int | None = None, free_floor_bytes: int = 0,
                 on_stopped: Callable[[str], None] | None = None, lossless: bool = False) -> None:
        """``free_floor_bytes``: the recording refuses to start, or stops, when the disk has less
        free; ``on_stopped(why)``: called once (on the writer thread) if it stops early.
        ``lossless``: a full queue makes the caller wait (offline writers: simulate, rerun)
        instead of dropping the message (the live loop must never wait on the disk)."""
        self.lossless = lossless
        self.path = path
        self.frame_rate_hz = frame_rate_hz
        self.jpeg_quality = jpeg_quality
        self.start_ns = time.time_ns() if start_ns is None else start_ns
        self.free_floor_bytes = free_floor_bytes
        self.on_stopped = on_stopped
        self.failure = ""  # why the recording stopped early ("" while it records or after a clean close)
        self.not_written = 0  # messages accepted but never written (the recording stopped, or closing gave up)
        check_room(path, free_floor_bytes)
        try:
            self._file = open(path, "xb")  # noqa: SIM115 - open for the session's life; never over an existing file
        except FileExistsError:
            raise RecordingRefused(f"{path}: exists; a recording is never written over another") from None
        try:  # locked before its first byte, until it is closed: retention elsewhere never deletes it
            fcntl.flock(self._file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:  # a file system without locks: say so, record anyway
            log.warning("recording %s: cannot lock it (%s); another service's retention could delete it", path,
                        exc.strerror or exc)
        # camera frames in chunks of their own: a damaged frame costs no tick (app.recording.mcap_out)
        self._writer = SessionWriter(self._file, CHUNK_BYTES, CHUNK_SECONDS, groups=[(IMAGE_TOPIC,)])
        self._channels: dict[str, int] = {}
        try:
            self._writer.start(library="omniformation")
            for topic, schema in TOPIC_SCHEMA.items():
                if topic in PROTOBUF_TOPICS:  # Foxglove's own schema, from its package
                    sid = self._writer.register_schema(schema, "protobuf", schema_data(PROTOBUF_TOPICS[topic]))
                    self._channels[topic] = self._writer.register_channel(topic, "protobuf", sid)
                else:
                    sid = self._writer.register_schema(schema, "jsonschema", json.dumps(SCHEMAS[schema]).encode())
                    self._channels[topic] = self._writer.register_channel(topic, "json", sid)
            # the session's config and the channel table, twice and outside every chunk: a damaged
            # first chunk (where MCAP puts the schema and channel records) or one damaged copy of
            # this record still leaves every other chunk readable (app.recording.reader)
            record = {**metadata, "start_ns": str(self.start_ns), CHANNELS_KEY: channel_table(self._channels)}
            record[METADATA_CRC_KEY] = metadata_crc(record)
            for _ in range(METADATA_COPIES):
                self._writer.add_metadata(METADATA_NAME, record)
        except OSError as exc:
            self._file.close()
            raise RecordingRefused(f"{path}: cannot write: {exc.strerror or exc}") from None
        self._abandon = False
        self._queue: queue.Queue[tuple[str, int, dict[str, Any] | Image] | None] = queue.Queue(maxsize=10_000)
        self._frame_slots = threading.Semaphore(MAX_FRAMES_WAITING)  # raw frames (~1 MB each) the writer may owe
        self._prev: TickState | None = None
        self._params = params
        self._clock = SessionClock()  # the session's time (s; never goes back)
        self._last_frame_t = -math.inf
        self._last_scan_t = -math.inf
        self.ticks = 0
        self.dropped = 0
        self._thread = threading.Thread(target=self._drain, name="omniformation-recorder", daemon=True)
        self._thread.start()
        self._put(PARAMS_TOPIC, 0.0, params_payload(params))

    def _ns(self, t: float) -> int:
        return self.start_ns + max(0, int(round(t * 1e9)))

    def _put(self, topic: str, t: float, payload: dict[str, Any] | Image) -> None:
        """Queue a message; JSON and JPEG encoding happen on the writer thread, not the loop's."""
        if self.failure:
            return  # the recording has stopped: nothing more is written
        item = (topic, self._ns(t), payload)
        while self.lossless and not self.failure and self._thread.is_alive():
            try:
                self._queue.put(item, timeout=0.5)
                return
            except queue.Full:
                continue
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1

    @property
    def recording(self) -> bool:
        return not self.failure and self._thread.is_alive()

    def on_tick(self, s: TickState) -> None:
        """The loop's subscriber: one tick (and the frame when one is due).

        Messages carry the session's time, which never goes back: after a reset the loop's own
        clock (each tick's ``t``, kept in its payload) starts again at 0, and the session's goes
        on from where it was (one tick later), so a replay's timeline and a report reach the
        whole session, before and after."""
        if self.failure:
            return
        t = self._clock(s.t)  # after a reset (its event came with the request) it goes on
        self._put(TICK_TOPIC, t, tick_payload(s))
        self._put(TF_TOPIC, t, transforms_payload(s, self._ns(t)))
        for kind, detail in tick_events(self._prev, s):
            self.event(t, kind, detail)
        if s.scan is not None and t - self._last_scan_t >= 1.0 / SCAN_HZ - 1e-9:
            self._last_scan_t = t
            self._put(SCAN_TOPIC, t, scan_payload(s.scan, self._ns(t)))
        if s.frame is not None and self.frame_rate_hz > 0 and t - self._last_frame_t >= 1.0 / self.frame_rate_hz - 1e-9:
            self._last_frame_t = t
            got = self._frame_slots.acquire(timeout=30.0) if self.lossless else self._frame_slots.acquire(blocking=False)
            if got:  # a stalled disk must not fill memory with frames
                self._put(IMAGE_TOPIC, t, s.frame)  # a published frame is never changed: encoded later
            else:
                self.dropped += 1
        self._prev = s
        self.ticks += 1

    def add_jpeg(self, t: float, jpeg: bytes) -> None:
        """One camera frame, already JPEG-encoded."""
        self._put(IMAGE_TOPIC, t, image_payload(self._ns(t), jpeg))

    def on_params(self, p: Params, source: str, notices: tuple[Any, ...]) -> None:
        """The store's subscriber: the new parameter set and what changed."""
        old, self._params = self._params, p
        for kind, detail in params_events(old, p, source):
            self.event(self._clock.last, kind, detail)
        self._put(PARAMS_TOPIC, self._clock.last, params_payload(p))

    def on_trial(self, trial: Any) -> None:
        """A step test's row (app.live.tuning.Trial): its message, and an event for the list."""
        payload = trial.payload()
        t = self._clock.last
        self._put(TRIAL_TOPIC, t, jsonable(payload))
        self.event(t, "trial", f"trial {payload['number']}: {payload['label']}, {payload['status']}")

    def event_now(self, kind: str, detail: str) -> None:
        """An event at the session's time now (the last tick's)."""
        self.event(self._clock.last, kind, detail)

    def event(self, t: float, kind: str, detail: str) -> None:
        self._put(EVENT_TOPIC, t, {"t": t, "kind": kind, "detail": detail})

    def _drain(self) -> None:
        written = self._file.tell()
        while not self._abandon:
            item = self._queue.get()
            if item is None:
                return
            topic, ns, payload = item
            if not isinstance(payload, dict):  # a camera frame (a synthetic one is rendered here, off the loop)
                self._frame_slots.release()
                ok, buf = cv2.imencode(".jpg", np.asarray(payload), [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
                if not ok:
                    continue
                payload = image_payload(ns, buf.tobytes())
            data = encode(topic, payload) if topic in PROTOBUF_TOPICS else json.dumps(payload, separators=(",", ":")).encode()
            try:
                self._writer.add_message(self._channels[topic], log_time=ns, data=data, publish_time=ns)
                if self.free_floor_bytes and self._file.tell() != written:  # a chunk went to disk: look again
                    written = self._file.tell()
                    free = free_bytes(self.path.parent)
                    if free < self.free_floor_bytes:
                        self._stop_early(f"the disk is nearly full ({free / 1e6:.0f} MB free, below the floor of"
                                         f" {self.free_floor_bytes / 1e6:.0f} MB)")
                        return
            except OSError as exc:
                self._stop_early(f"writing failed: {exc.strerror or exc}")
                return

    def _stop_early(self, why: str) -> None:
        """On the writer thread: end the file as well as the disk lets us, say why, drop the rest."""
        self.failure = why
        self.not_written += self._queue.qsize() + 1
        self._finish_file()
        log.error("recording %s stopped: %s", self.path, why)
        while True:  # what is queued will never be written: let the loop's frames go
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                break
            if item is not None and not isinstance(item[2], dict):
                self._frame_slots.release()
        if self.on_stopped is not None:
            try:
                self.on_stopped(why)
            except Exception:
                log.exception("recording stop listener failed")

    def _finish_file(self) -> None:
        """Summary and index if the disk takes them; the file is closed either way (a file
        without its summary is still read up to its last complete chunk)."""
        try:
            # the counts again, with a CRC, after the last chunk: a damaged summary leaves them known
            self._writer.flush()
            counts = {COUNTS_KEY: json.dumps({str(c): n for c, n in self._writer.message_counts.items() if n},
                                             separators=(",", ":"))}
            counts[METADATA_CRC_KEY] = metadata_crc(counts)
            self._writer.add_metadata(COUNTS_NAME, counts)
            self._writer.finish()
        except (OSError, ValueError):
            pass
        try:
            self._file.close()
        except OSError:
            pass

    def ticks_in_file(self) -> int:
        """Ticks the file holds, whole and readable. A recording that stopped early (a full disk)
        or gave up closing is read back, since a failed write may have left part of a chunk; else
        every tick in a chunk written whole."""
        if self.failure and not self._thread.is_alive():
            from app.recording.reader import RecordingError, read_recording

            try:
                rec = read_recording(self.path)
            except RecordingError:
                return 0
            try:
                return len(rec.t)
            finally:
                rec.close()
        return self._writer.messages_written.get(self._channels[TICK_TOPIC], 0)

    def closing_line(self) -> str:
        """What the service prints when the session ends: ticks the loop published, ticks in the
        file, ticks not written, and why; they add up."""
        in_file = self.ticks_in_file()
        if not self.failure and in_file == self.ticks:
            return f"recording finished: {self.path.name} ({in_file} ticks)"
        why = f" ({self.failure})" if self.failure else f" ({self.dropped} dropped: the disk was too slow)"
        return (f"recording {'stopped early' if self.failure else 'finished'}: {self.path.name} holds {in_file} of"
                f" the {self.ticks} ticks it was given; {self.ticks - in_file} were not written{why}")

    def close(self) -> None:
        """Write what is queued, then the summary and index: a complete file. Never waits on a
        slow or dead disk longer than ``CLOSE_TIMEOUT_S``."""
        try:
            self._queue.put(None, timeout=CLOSE_TIMEOUT_S / 2)
        except queue.Full:
            pass
        self._thread.join(CLOSE_TIMEOUT_S)
        if self._thread.is_alive():  # the disk does not take the bytes: leave the file as it is
            self._abandon = True
            self.not_written += self._queue.qsize()
            if not self.failure:
                self.failure = f"closing gave up after {CLOSE_TIMEOUT_S:g} s (the disk did not keep up)"
            return
        if not self.failure:
            self._finish_file()
