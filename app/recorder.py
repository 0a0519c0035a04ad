"""Recording sessions to MCAP and reading them back (with recovery of cut-off files).

Channels (JSON message encoding, JSON-schema schemas, so a recording opens in Foxglove /
Lichtblick as well as in `omniformation replay`):

=========================== =============================== ==========================================
topic                       schema                          what
=========================== =============================== ==========================================
/omniformation/tick         omniformation.Tick              every tick: estimated and true poses, raw and
                                                            filtered headings, tracked, desired positions,
                                                            slots, assignment, errors, V, commands, leader
                                                            pose (odometry) and velocity, gains, stage times
/tf                         foxglove.FrameTransforms        leader in the world, followers (estimate) in the
                                                            leader frame, followers (truth) in the world
/camera/image               foxglove.CompressedImage        the leader's frame as JPEG, ``frame_rate_hz``
/omniformation/events       omniformation.Event             gain / target / preset changes, STOP, follower
                                                            lost / found, link state, vision phase
/omniformation/params       omniformation.Params            the full parameter set at start and on change
=========================== =============================== ==========================================

Metadata record ``omniformation``: the config and scenario text used, the command line.

Crash safety: messages are written in zstd chunks of at most ``CHUNK_BYTES``; SIGINT /
SIGTERM finish the file (summary and index). A file cut off by SIGKILL or power loss is
still read up to its last complete chunk: at most ``CHUNK_BYTES`` of messages — about one
second of a session with camera frames at 10 Hz — are lost.
"""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import math
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from mcap.exceptions import McapError
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from app.loop import TickState
from app.params import Params

CHUNK_BYTES = 256 * 1024
TICK_TOPIC = "/omniformation/tick"
TF_TOPIC = "/tf"
IMAGE_TOPIC = "/camera/image"
EVENT_TOPIC = "/omniformation/events"
PARAMS_TOPIC = "/omniformation/params"
DEFAULT_FRAME_RATE_HZ = 10.0
MAX_FRAMES_WAITING = 30  # raw frames queued for JPEG encoding on the writer thread (3 s at 10 Hz)

_NUM_ARRAY = {"type": "array", "items": {"type": ["number", "null"]}}
_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_VEC3 = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_QUAT = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}

SCHEMAS: dict[str, dict[str, Any]] = {
    "omniformation.Tick": {
        "type": "object",
        "title": "omniformation.Tick",
        "description": "One loop tick. Leader frame: x right, y forward; SI units, radians.",
        "properties": {
            "tick": {"type": "integer"}, "t": {"type": "number"},
            "leader": _NUM_ARRAY, "leader_twist": _NUM_ARRAY,
            "p_est": {"type": "array"}, "a_est": _NUM_ARRAY, "a_raw": _NUM_ARRAY, "tracked": {"type": "array"},
            "p_true": {"type": "array"}, "a_true": _NUM_ARRAY, "followers_world": {"type": "array"},
            "p_d": {"type": "array"}, "slot_targets": {"type": "array"}, "assignment": {"type": "array"},
            "commands": {"type": "array"}, "a_err": _NUM_ARRAY, "v_lyap": _NUM_ARRAY,
            "gains": {"type": "object"}, "params_version": {"type": "integer"},
            "stopped": {"type": "boolean"}, "paused": {"type": "boolean"}, "link_state": {"type": "string"},
            "rate_hz": {"type": "number"}, "stage_ms": {"type": "object"}, "phase": {"type": "string"},
            "probing": {"type": "integer"}, "windows": {"type": "array"}, "hues_deg": _NUM_ARRAY,
        },
    },
    "foxglove.FrameTransforms": {
        "type": "object",
        "title": "foxglove.FrameTransforms",
        "properties": {"transforms": {"type": "array", "items": {
            "type": "object", "title": "foxglove.FrameTransform",
            "properties": {"timestamp": _TIME, "parent_frame_id": {"type": "string"},
                           "child_frame_id": {"type": "string"}, "translation": _VEC3, "rotation": _QUAT}}}},
    },
    "foxglove.CompressedImage": {
        "type": "object",
        "title": "foxglove.CompressedImage",
        "properties": {"timestamp": _TIME, "frame_id": {"type": "string"},
                       "data": {"type": "string", "contentEncoding": "base64"}, "format": {"type": "string"}},
    },
    "omniformation.Event": {
        "type": "object", "title": "omniformation.Event",
        "properties": {"t": {"type": "number"}, "kind": {"type": "string"}, "detail": {"type": "string"}},
    },
    "omniformation.Params": {"type": "object", "title": "omniformation.Params"},
}
TOPIC_SCHEMA = {TICK_TOPIC: "omniformation.Tick", TF_TOPIC: "foxglove.FrameTransforms",
                IMAGE_TOPIC: "foxglove.CompressedImage", EVENT_TOPIC: "omniformation.Event",
                PARAMS_TOPIC: "omniformation.Params"}


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (np.floating, float)):
        f = float(x)
        # 7 significant digits: micrometres and microradians, and files half the size
        return float(f"{f:.7g}") if math.isfinite(f) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def tick_payload(s: TickState) -> dict[str, Any]:
    """A TickState as the JSON object recorded on /omniformation/tick (no image)."""
    d = {f.name: getattr(s, f.name) for f in dataclasses.fields(s) if f.name != "frame"}
    d["gains"] = s.gains.as_dict()
    return _jsonable(d)  # type: ignore[no-any-return]


def params_payload(p: Params) -> dict[str, Any]:
    d = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
    d["gains"] = p.gains.as_dict()
    return _jsonable(d)  # type: ignore[no-any-return]


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _image_payload(ns: int, jpeg: bytes) -> dict[str, Any]:
    """A foxglove.CompressedImage message."""
    return {"timestamp": _stamp(ns), "frame_id": "camera", "data": base64.b64encode(jpeg).decode(), "format": "jpeg"}


def _yaw_quat(yaw: float) -> dict[str, float]:
    return {"x": 0.0, "y": 0.0, "z": math.sin(yaw / 2), "w": math.cos(yaw / 2)}


def transforms_payload(s: TickState, ns: int) -> dict[str, Any]:
    ts = _stamp(ns)
    lx, ly, lth = (float(v) for v in s.leader)
    out = [{"timestamp": ts, "parent_frame_id": "world", "child_frame_id": "leader",
            "translation": {"x": lx, "y": ly, "z": 0.0}, "rotation": _yaw_quat(lth - math.pi / 2)}]
    for i in range(s.n):
        px, py = s.p_est[i]
        if np.isfinite(px) and np.isfinite(py) and np.isfinite(s.a_est[i]):
            out.append({"timestamp": ts, "parent_frame_id": "leader", "child_frame_id": f"follower{i + 1}",
                        "translation": {"x": float(px), "y": float(py), "z": 0.0},
                        "rotation": _yaw_quat(float(s.a_est[i]))})
        fx, fy, fth = (float(v) for v in s.followers_world[i])
        out.append({"timestamp": ts, "parent_frame_id": "world", "child_frame_id": f"follower{i + 1}_true",
                    "translation": {"x": fx, "y": fy, "z": 0.0}, "rotation": _yaw_quat(fth)})
    return {"transforms": out}


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
    if prev.phase != s.phase:
        ev.append(("phase", f"vision {prev.phase} -> {s.phase}"))
    if prev.stopped != s.stopped:
        ev.append(("stop", "STOP: every follower at zero" if s.stopped else "STOP released"))
    return ev


def params_events(old: Params, new: Params, source: str) -> list[tuple[str, str]]:
    """What an operator change did, in words."""
    ev: list[tuple[str, str]] = []
    og, ng = old.gains.as_dict(), new.gains.as_dict()
    changed = [f"{k} {og[k]:g} -> {ng[k]:g}" for k in ng if og[k] != ng[k]]
    if changed:
        ev.append(("gain", ", ".join(changed)))
    if old.slots.shape != new.slots.shape or not np.array_equal(old.slots, new.slots):
        kind = "preset" if "preset" in source else "target"
        ev.append((kind, f"{source.split(' ', 1)[-1] if kind == 'preset' else 'slots'}: "
                   + "; ".join(f"({x:.2f}, {y:.2f})" for x, y in new.slots)))
    for key in ("leader_mode", "leader_speed_mps", "leader_turn_deg_s", "n_followers", "paused"):
        if getattr(old, key) != getattr(new, key):
            ev.append(("setting", f"{key} {getattr(old, key)} -> {getattr(new, key)}"))
    if old.reset_requests != new.reset_requests:
        ev.append(("reset", "team reset"))
    return ev


class Recorder:
    """Writes a session: subscribe ``on_tick`` to the loop and ``on_params`` to the store.

    Messages are queued and written by one writer thread, so the loop never waits on the disk.
    """

    def __init__(self, path: Path, metadata: dict[str, str], params: Params,
                 frame_rate_hz: float = DEFAULT_FRAME_RATE_HZ, jpeg_quality: int = 80,
                 start_ns: int | None = None) -> None:
        self.path = path
        self.frame_rate_hz = frame_rate_hz
        self.jpeg_quality = jpeg_quality
        self.start_ns = time.time_ns() if start_ns is None else start_ns
        self._file = open(path, "wb")
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="omniformation")
        self._channels: dict[str, int] = {}
        for topic, schema in TOPIC_SCHEMA.items():
            sid = self._writer.register_schema(schema, "jsonschema", json.dumps(SCHEMAS[schema]).encode())
            self._channels[topic] = self._writer.register_channel(topic, "json", sid)
        self._writer.add_metadata("omniformation", {**metadata, "start_ns": str(self.start_ns)})
        self._queue: queue.Queue[tuple[str, int, dict[str, Any] | np.ndarray] | None] = queue.Queue(maxsize=10_000)
        self._frame_slots = threading.Semaphore(MAX_FRAMES_WAITING)  # raw frames (~1 MB each) the writer may owe
        self._prev: TickState | None = None
        self._params = params
        self._last_t = 0.0
        self._last_frame_t = -math.inf
        self.ticks = 0
        self.dropped = 0
        self._thread = threading.Thread(target=self._drain, name="omniformation-recorder", daemon=True)
        self._thread.start()
        self._put(PARAMS_TOPIC, 0.0, params_payload(params))

    def _ns(self, t: float) -> int:
        return self.start_ns + max(0, int(round(t * 1e9)))

    def _put(self, topic: str, t: float, payload: dict[str, Any] | np.ndarray) -> None:
        """Queue a message; JSON and JPEG encoding happen on the writer thread, not the loop's."""
        try:
            self._queue.put_nowait((topic, self._ns(t), payload))
        except queue.Full:
            self.dropped += 1

    def on_tick(self, s: TickState) -> None:
        """The loop's subscriber: one tick (and the frame when one is due)."""
        self._last_t = s.t
        self._put(TICK_TOPIC, s.t, tick_payload(s))
        self._put(TF_TOPIC, s.t, transforms_payload(s, self._ns(s.t)))
        for kind, detail in tick_events(self._prev, s):
            self.event(s.t, kind, detail)
        if s.frame is not None and self.frame_rate_hz > 0 and s.t - self._last_frame_t >= 1.0 / self.frame_rate_hz - 1e-9:
            self._last_frame_t = s.t
            if self._frame_slots.acquire(blocking=False):  # a stalled disk must not fill memory with frames
                self._put(IMAGE_TOPIC, s.t, s.frame)  # a published frame is never changed: encoded later
            else:
                self.dropped += 1
        self._prev = s
        self.ticks += 1

    def add_jpeg(self, t: float, jpeg: bytes) -> None:
        """One camera frame, already JPEG-encoded."""
        self._put(IMAGE_TOPIC, t, _image_payload(self._ns(t), jpeg))

    def on_params(self, p: Params, source: str, notices: tuple[Any, ...]) -> None:
        """The store's subscriber: the new parameter set and what changed."""
        old, self._params = self._params, p
        for kind, detail in params_events(old, p, source):
            self.event(self._last_t, kind, detail)
        self._put(PARAMS_TOPIC, self._last_t, params_payload(p))

    def event(self, t: float, kind: str, detail: str) -> None:
        self._put(EVENT_TOPIC, t, {"t": t, "kind": kind, "detail": detail})

    def _drain(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            topic, ns, payload = item
            if not isinstance(payload, dict):  # a camera frame (a synthetic one is rendered here, off the loop)
                self._frame_slots.release()
                ok, buf = cv2.imencode(".jpg", np.asarray(payload), [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
                if not ok:
                    continue
                payload = _image_payload(ns, buf.tobytes())
            data = json.dumps(payload, separators=(",", ":")).encode()
            self._writer.add_message(self._channels[topic], log_time=ns, data=data, publish_time=ns)

    def close(self) -> None:
        """Write what is queued, then the summary and index: a complete file."""
        self._queue.put(None)
        self._thread.join()
        self._writer.finish()
        self._file.close()


# ---------------------------------------------------------------- reading


class RecordingError(ValueError):
    """A file that is not a readable recording: one line for people."""


@dataclass
class Recording:
    path: Path
    metadata: dict[str, str]
    ticks: list[dict[str, Any]]
    frames: list[tuple[float, bytes]]  # (t, JPEG); while reading: (log time ns, JPEG)
    events: list[dict[str, Any]]
    params: list[tuple[float, dict[str, Any]]]
    complete: bool
    bytes_total: int
    bytes_read: int  # up to the end of the last complete record
    channels: dict[str, str] = field(default_factory=dict)  # topic -> schema name

    @property
    def t(self) -> np.ndarray:
        return np.array([tk["t"] for tk in self.ticks])

    def loss_note(self) -> str:
        if self.complete:
            return ""
        lost = self.bytes_total - self.bytes_read
        last = self.ticks[-1]["t"] if self.ticks else 0.0
        return (f"{self.path.name}: the file was cut off (no summary); recovered {len(self.ticks)} ticks up to"
                f" t = {last:.2f} s; the last {lost} bytes (an unfinished chunk, at most {CHUNK_BYTES // 1024} KiB)"
                " could not be read")


def read_recording(path: Path) -> Recording:
    """Every message of a recording, or as many as a cut-off file still holds.

    Reads sequentially, so a file without summary (writer killed) is read up to its
    last complete chunk. A file that is not MCAP at all raises :class:`RecordingError`.
    """
    if not path.is_file():
        raise RecordingError(f"{path}: no such recording")
    data = path.read_bytes()
    total = len(data)
    stream = io.BytesIO(data)
    reader = StreamReader(stream, validate_crcs=True)
    schemas: dict[int, str] = {}
    channels: dict[int, str] = {}
    rec = Recording(path, {}, [], [], [], [], False, total, 0)
    good = 0
    try:
        for record in reader.records:
            if isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                channels[record.id] = record.topic
                rec.channels[record.topic] = schemas.get(record.schema_id, "")
            elif isinstance(record, Metadata):
                if record.name == "omniformation":
                    rec.metadata = dict(record.metadata)
            elif isinstance(record, Message):
                _take(rec, channels.get(record.channel_id, ""), record.data)
            elif isinstance(record, Footer):
                rec.complete = True
            good = stream.tell()
    except Exception as exc:  # noqa: BLE001 - a cut-off or garbage stream raises assorted errors
        if not rec.channels:
            kind = "not an MCAP file" if isinstance(exc, McapError) or good == 0 else "not a readable recording"
            raise RecordingError(f"{path.name}: {kind} ({type(exc).__name__})") from None
    rec.bytes_read = good if not rec.complete else total
    start_ns = int(rec.metadata.get("start_ns", "0") or 0)
    rec.frames = [((ns - start_ns) / 1e9, jpg) for ns, jpg in rec.frames]
    if TICK_TOPIC not in rec.channels:
        raise RecordingError(f"{path.name}: an MCAP file, but not an omniformation recording (no {TICK_TOPIC})")
    if not rec.ticks:
        raise RecordingError(f"{path.name}: the recording holds no complete tick (cut off in its first chunk)")
    return rec


def _take(rec: Recording, topic: str, data: bytes) -> None:
    if topic == TICK_TOPIC:
        rec.ticks.append(json.loads(data))
    elif topic == IMAGE_TOPIC:
        msg = json.loads(data)
        ns = msg["timestamp"]["sec"] * 1_000_000_000 + msg["timestamp"]["nsec"]
        rec.frames.append((ns, base64.b64decode(msg["data"])))
    elif topic == EVENT_TOPIC:
        rec.events.append(json.loads(data))
    elif topic == PARAMS_TOPIC:
        p = json.loads(data)
        rec.params.append((float(rec.ticks[-1]["t"]) if rec.ticks else 0.0, p))


def json_floats(x: Any, dtype: Any = np.float64) -> np.ndarray:
    """A recorded JSON (nested) list as an array; JSON null (a NaN when written) back to NaN."""
    a = np.array(x if x is not None else [], dtype=object)
    a = np.where(a == None, np.nan, a)  # noqa: E711 - JSON null is NaN
    return a.astype(dtype)


def tick_from_payload(d: dict[str, Any], frame: np.ndarray | None = None) -> TickState:
    """A recorded tick back as the TickState the loop published (the frame from /camera/image)."""
    from core.types import Gains

    n = len(d["a_est"])
    return TickState(
        tick=int(d["tick"]), t=float(d["t"]), leader=json_floats(d["leader"]), leader_twist=tuple(d["leader_twist"]),
        followers_world=json_floats(d["followers_world"]).reshape(n, 3), p_est=json_floats(d["p_est"]).reshape(n, 2),
        a_est=json_floats(d["a_est"]), tracked=np.array(d["tracked"], dtype=bool),
        p_true=json_floats(d["p_true"]).reshape(n, 2), a_true=json_floats(d["a_true"]), p_d=json_floats(d["p_d"]).reshape(n, 2),
        slot_targets=json_floats(d["slot_targets"]).reshape(-1, 2), assignment=np.array(d["assignment"], dtype=np.intp),
        commands=json_floats(d["commands"]).reshape(n, 2), a_err=json_floats(d["a_err"]), v_lyap=json_floats(d["v_lyap"]),
        gains=Gains(**d["gains"]), params_version=int(d["params_version"]), stopped=bool(d["stopped"]),
        paused=bool(d["paused"]), link_state=str(d["link_state"]), rate_hz=float(d["rate_hz"]),
        stage_ms=dict(d.get("stage_ms") or {}), phase=str(d.get("phase", "truth")), probing=int(d.get("probing", -1)),
        a_raw=json_floats(d["a_raw"]) if d.get("a_raw") is not None else None, frame=frame,
        windows=np.array(d["windows"], dtype=np.int64).reshape(n, 4) if d.get("windows") is not None else None,
        hues_deg=json_floats(d["hues_deg"]) if d.get("hues_deg") is not None else None,
    )


def params_from_recording(rec: Recording) -> Params:
    """The parameter set in force when the recording started."""
    if not rec.params:
        return Params()
    from core.types import Gains

    d = rec.params[0][1]
    return Params(gains=Gains(**d["gains"]), leader_mode=d["leader_mode"], leader_speed_mps=d["leader_speed_mps"],
                  leader_turn_deg_s=d["leader_turn_deg_s"], slots=np.array(d["slots"], dtype=float).reshape(-1, 2),
                  n_followers=int(d["n_followers"]))
