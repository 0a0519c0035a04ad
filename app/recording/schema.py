"""What a recording holds: its channels, their schemas, and the payloads both ways
(a TickState or Params to JSON and back).

Channels (our own in JSON with JSON-schema schemas; /tf, /camera/image and /scan in protobuf
with Foxglove's own published schemas, app.recording.foxglove; so a recording opens in
Foxglove / Lichtblick as well as in `omniformation replay`):

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
/omniformation/trials       omniformation.Trial             each step test (app.live.tuning): the test, the
                                                            gains, when it started, its scores per follower
=========================== =============================== ==========================================

Metadata record ``omniformation`` (written twice, before the first chunk): the config and
scenario text used, the command line, and the channel table (``channels``: id -> topic,
encoding, schema), so that a damaged first chunk (which holds MCAP's schema and channel
records) costs that chunk and no more.

Crash safety: messages are written in zstd chunks that close at the first of ``CHUNK_BYTES`` and
``CHUNK_SECONDS`` of session time; camera frames have chunks of their own; every chunk carries the
schema and channel records of its messages (app.recording.mcap_out). One damaged chunk costs at
most about a second of ticks (or of frames, never both); SIGINT / SIGTERM finish the file
(summary and index), and a file cut off by SIGKILL or power loss is read up to its last complete
chunk: all but about its last second. The writer keeps 48 bytes per chunk until the file closes
(about 0.35 MB an hour at two chunks a second).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from app.params import Params
from app.tick import TickState
from core.obstacles import Obstacle
from core.vision.freespace import Scan

CHUNK_BYTES = 1024 * 1024
CHUNK_SECONDS = 1.0  # a chunk closes after this much session time (or CHUNK_BYTES, whichever first)
METADATA_NAME = "omniformation"  # the metadata record that marks a file as one of ours
METADATA_COPIES = 2  # it is written twice, before the first chunk
CHANNELS_KEY = "channels"  # in it: the channel table, {"id": [topic, encoding, schema]} (JSON)
METADATA_CRC_KEY = "crc"  # and a CRC of the rest (app.recording.reader.metadata_crc): a damaged copy is known
COUNTS_NAME = "omniformation.counts"  # the last record before the summary: messages written per channel id (JSON
COUNTS_KEY = "channel_message_counts"  # in COUNTS_KEY) and its CRC, so a damaged summary does not take the count
TICK_TOPIC = "/omniformation/tick"
TF_TOPIC = "/tf"
IMAGE_TOPIC = "/camera/image"
EVENT_TOPIC = "/omniformation/events"
PARAMS_TOPIC = "/omniformation/params"
SCAN_TOPIC = "/scan"
TRIAL_TOPIC = "/omniformation/trials"
SCAN_HZ = 10.0  # free-space scans recorded per second (each is 360 ranges)

_NUM_ARRAY = {"type": "array", "items": {"type": ["number", "null"]}}
_NUM_ARRAY_OR_NULL = {"type": ["array", "null"], "items": {"type": ["number", "null"]}}  # None when not measured
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
            "p_est": {"type": "array"}, "a_est": _NUM_ARRAY, "a_raw": _NUM_ARRAY_OR_NULL, "tracked": {"type": "array"},
            "p_true": {"type": "array"}, "a_true": _NUM_ARRAY, "followers_world": {"type": "array"},
            "p_d": {"type": "array"}, "slot_targets": {"type": "array"}, "assignment": {"type": "array"},
            "commands": {"type": "array"}, "a_err": _NUM_ARRAY, "v_lyap": _NUM_ARRAY,
            "gains": {"type": "object"}, "params_version": {"type": "integer"},
            "stopped": {"type": "boolean"}, "paused": {"type": "boolean"}, "link_state": {"type": "string"},
            "rate_hz": {"type": "number"}, "stage_ms": {"type": "object"}, "phase": {"type": "string"},
            "probing": {"type": "integer"}, "windows": {"type": ["array", "null"]}, "hues_deg": _NUM_ARRAY_OR_NULL,
            "safety": {"type": "string"}, "safety_changed": _NUM_ARRAY_OR_NULL, "min_distance_m": {"type": ["number", "null"]},
            "safety_active": {"type": ["array", "null"]},
            "obstacles": {"type": ["array", "null"], "description": "obstacle points the leader knows, leader frame, m"},
            "goal": {"type": ["array", "null"]}, "heading": {"type": ["number", "null"]},
            "formation_scale": {"type": "number"}, "goal_reached": {"type": "boolean"},
            "limits": {"type": ["array", "null"], "description": "per follower, bits of the active saturations and"
                       " limits: 1 eq. 4, 2 eq. 12, 4 v limit, 8 omega limit, 16 safety filter"},
            "v_rate": {"type": ["array", "null"], "description": "dV/dt per follower, m^2/s (eq. 21)"},
            "latency_ms": {"type": ["number", "null"], "description": "from what the tick observed (a camera"
                           " frame's arrival) to its commands written to the link, ms"},
            "fresh": {"type": "boolean", "description": "the tick observed anew (false: the last frame stood)"},
            "leader_waits": {"type": "string", "description": "why the leader stands still (STOP, a release waiting"
                             " for the team); empty when it may drive"},
        },
    },
    "omniformation.Event": {
        "type": "object", "title": "omniformation.Event",
        "properties": {"t": {"type": "number"}, "kind": {"type": "string"}, "detail": {"type": "string"}},
    },
    "omniformation.Params": {"type": "object", "title": "omniformation.Params"},
    "omniformation.Trial": {
        "type": "object", "title": "omniformation.Trial",
        "description": "One step test: settling time to 2 cm (s, null: not within the window), overshoot (m),"
                       " steady error RMS (m), effort (integral of the mean squared wheel speed, m^2/s)",
        "properties": {"number": {"type": "integer"}, "test": {"type": "object"}, "label": {"type": "string"},
                       "gains": {"type": "object"}, "t0": {"type": "number"}, "status": {"type": "string"},
                       "followers": {"type": ["array", "null"]}, "team": {"type": ["object", "null"]}},
    },
}
TOPIC_SCHEMA = {TICK_TOPIC: "omniformation.Tick", TF_TOPIC: "foxglove.FrameTransforms",
                IMAGE_TOPIC: "foxglove.CompressedImage", EVENT_TOPIC: "omniformation.Event",
                PARAMS_TOPIC: "omniformation.Params", SCAN_TOPIC: "foxglove.LaserScan",
                TRIAL_TOPIC: "omniformation.Trial"}


def jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
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
    d = {f.name: getattr(s, f.name) for f in dataclasses.fields(s) if f.name not in ("frame", "scan")}
    d["gains"] = s.gains.as_dict()
    if s.obstacles is not None:  # centimetres are what the scan resolves
        d["obstacles"] = np.round(np.asarray(s.obstacles, dtype=np.float64), 2)
    return jsonable(d)  # type: ignore[no-any-return]  # a dict in, the same keys out


def scan_payload(scan: Scan, ns: int) -> dict[str, Any]:
    """A foxglove.LaserScan message: angles counter-clockwise from the leader frame's +x (its
    right), as Foxglove reads them; our bearings count from straight ahead (+y)."""
    b = scan.bearings
    return {"timestamp": _stamp(ns), "frame_id": "leader",
            "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
            "start_angle": float(b[0] + math.pi / 2), "end_angle": float(b[-1] + math.pi / 2),
            "ranges": jsonable(scan.ranges), "intensities": []}


def params_payload(p: Params) -> dict[str, Any]:
    d = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
    d["gains"] = p.gains.as_dict()
    return jsonable(d)  # type: ignore[no-any-return]  # a dict in, the same keys out


def _stamp(ns: int) -> dict[str, int]:
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def image_payload(ns: int, jpeg: bytes) -> dict[str, Any]:
    """A foxglove.CompressedImage message (encoded as protobuf by app.recording.foxglove). Its
    frame is the leader's, which /tf places: the camera looks along the leader's vertical axis."""
    return {"timestamp": _stamp(ns), "frame_id": "leader", "data": jpeg, "format": "jpeg"}


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


def json_floats(x: Any, dtype: Any = np.float64) -> np.ndarray:
    """A recorded JSON (nested) list as an array; JSON null (a NaN when written) back to NaN."""
    try:
        return np.array(x if x is not None else [], dtype=dtype)  # no null inside: the fast way
    except (TypeError, ValueError):
        pass
    a = np.array(x, dtype=object)
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
        safety=str(d.get("safety", "")),
        safety_changed=json_floats(d["safety_changed"]) if d.get("safety_changed") is not None else None,
        min_distance_m=float(d["min_distance_m"]) if d.get("min_distance_m") is not None else float("nan"),
        safety_active=np.array(d["safety_active"], dtype=bool) if d.get("safety_active") is not None else None,
        obstacles=json_floats(d["obstacles"]).reshape(-1, 2) if d.get("obstacles") is not None else None,
        goal=(float(d["goal"][0]), float(d["goal"][1])) if d.get("goal") is not None else None,
        heading=float(d["heading"]) if d.get("heading") is not None else float("nan"),
        formation_scale=float(d.get("formation_scale", 1.0)), goal_reached=bool(d.get("goal_reached", False)),
        limits=np.array(d["limits"], dtype=np.int64) if d.get("limits") is not None else None,
        v_rate=json_floats(d["v_rate"]) if d.get("v_rate") is not None else None,
        leader_waits=str(d.get("leader_waits", "")),
        latency_ms=float(d["latency_ms"]) if d.get("latency_ms") is not None else float("nan"),
        fresh=bool(d.get("fresh", True)),
    )


def scenario_obstacles(metadata: dict[str, str]) -> tuple[Obstacle, ...]:
    """The boxes of the scenario a recording was made with (its text is in the metadata); none
    when it had none or its text no longer parses."""
    text = metadata.get("scenario_toml", "")
    if "[[obstacles]]" not in text:
        return ()
    from core.config import ConfigError, parse_scenario

    try:
        return parse_scenario(text, "the recorded scenario").obstacles
    except ConfigError:
        return ()
