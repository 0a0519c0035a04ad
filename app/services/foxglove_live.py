"""Foxglove live: a session served to Foxglove by Foxglove's own SDK (``foxglove-sdk``: its
WebSocket server, no hand-written protocol), view-only (docs/foxglove.md).

An adapter at the edge: it is handed what the loop already publishes (each TickState, as the
recorder is; each parameter set, as the recorder is) and never reaches into the loop. The loop
only puts the state in a bounded queue (a full queue drops the state and counts it); a thread of
its own turns it into messages:

* the recording's channels, with the recording's encoders and schemas (app.recording.schema,
  app.recording.foxglove): /omniformation/tick, /tf, /camera/image, /scan, /omniformation/events,
  /omniformation/params, /omniformation/trials;
* ``/omniformation/scene``, a ``foxglove.SceneUpdate`` per tick: the leader, each follower in its
  page colour with its heading, the slots and the formation, the obstacles as the leader knows
  them and the safety rings (a red ring on a follower the safety filter holds back), in the
  leader frame that /tf places in the world;
* ``/omniformation/log``: each event again as a ``foxglove.Log`` (STOP, a follower lost, the
  link and the safety filter as warnings), for Foxglove's Log panel.

Every message carries the session's time (app.tick.SessionClock, as the recording). Work a
message needs (JSON, JPEG, the scene) is skipped while no client subscribes to its channel.
The server advertises no capability: a client can neither publish nor set a parameter.
"""

from __future__ import annotations

import json
import logging
import math
import queue
import re
import threading
import time
from collections.abc import Callable
from typing import Any

import cv2
import foxglove
import numpy as np
from foxglove.channels import LogChannel, SceneUpdateChannel
from foxglove.messages import (ArrowPrimitive, Color, CubePrimitive, LinePrimitive, LinePrimitiveLineType, Log, LogLevel, Point3,
                               Pose, Quaternion, SceneEntity, SceneEntityDeletion, SceneUpdate, SpherePrimitive,
                               TextPrimitive, Timestamp, Vector3)

from core.camera.render.looks import hue_rgb

from app.dashboard.gate import is_loopback
from app.params import Params, params_events
from app.refusals import refuse
from app.recording.foxglove import PROTOBUF_TOPICS, encode, schema_data
from app.recording.schema import (EVENT_TOPIC, IMAGE_TOPIC, PARAMS_TOPIC, SCAN_HZ, SCAN_TOPIC, SCHEMAS, TF_TOPIC,
                                  TICK_TOPIC, TOPIC_SCHEMA, TRIAL_TOPIC, image_payload, jsonable, params_payload,
                                  scan_payload, tick_payload, transforms_payload)
from app.recording.writer import tick_events
from app.tick import SessionClock, TickState
from core.camera.render.looks import follower_rgb
from core.camera.guide import WORKING_RING_M

SCENE_TOPIC = "/omniformation/scene"
LOG_TOPIC = "/omniformation/log"  # the events again, as foxglove.Log: Foxglove's Log panel is the event log
WARNING_KINDS = {"stop", "lost", "safety", "link", "fault"}
DEFAULT_PORT = 8765  # Foxglove's own default
PARAMS_EVERY_S = 1.0  # the parameter set again, for a client that joins later (a live stream keeps nothing)
MAX_WAITING = 300  # states queued for the server's thread (10 s at 30 Hz); beyond, the newest is dropped
BACKLOG = 512  # messages the SDK buffers per client before it drops that client's oldest (about 2 s of every channel)
SLOT_Z_M = 0.16
FOLLOWER_RADIUS_M = 0.11  # half the diagonal of the follower's footprint drawn (0.25 x 0.15 m): the safety ring's

log = logging.getLogger(__name__)
_ADDRESS = re.compile(r"\[[0-9A-Fa-f:.]+\]:\d+|\d{1,3}(?:\.\d{1,3}){3}:\d+")


class _SdkLines(logging.Handler):
    """The SDK's own warnings and errors (one per refused client message: ``Invalid message from
    ADDR: why``) through the rate-limited refusals (app.refusals): a client that sends garbage
    cannot fill the log. Its lower levels are dropped, as Python's default handling dropped them."""

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        m = _ADDRESS.search(text)
        head = text[:m.start()] if m else text.split(":", 1)[0]
        kind = re.sub(r"\s+(from|for|to|by)\s*$", "", head.strip()).lower() or "message"
        refuse(f"foxglove: {kind}", m.group(0) if m else "a client",
               text[m.end():].lstrip(": ") if m else text)


def quiet_sdk() -> None:
    """Route the SDK's log records (the ``foxglove`` logger's) through app.refusals, once."""
    sdk = logging.getLogger("foxglove")
    if not any(isinstance(h, _SdkLines) for h in sdk.handlers):
        sdk.addHandler(_SdkLines(logging.WARNING))
        sdk.propagate = False


class FoxgloveRefused(ValueError):
    """The server cannot start (a host without TLS, a port in use, bad certificate): one line."""


def _rgba(rgb: tuple[int, int, int], a: float = 1.0) -> Color:
    return Color(r=rgb[0] / 255, g=rgb[1] / 255, b=rgb[2] / 255, a=a)


def _pose(x: float, y: float, z: float, yaw: float = 0.0) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z),
                orientation=Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))


def _circle(cx: float, cy: float, r: float, z: float, segments: int = 36) -> list[Point3]:
    ang = np.linspace(0.0, 2 * math.pi, segments, endpoint=False)
    return [Point3(x=cx + r * math.cos(a), y=cy + r * math.sin(a), z=z) for a in ang]


LEADER_BLUE, SLOT_RED, RING_BLUE, KNOWN_ORANGE, SAFETY_RED = ((40, 70, 140), (200, 40, 40), (120, 160, 220),
                                                              (240, 140, 0), (220, 30, 30))


def scene_update(s: TickState, ns: int) -> SceneUpdate:
    """What the page's 3D view shows (app.dashboard.scene), as one foxglove.SceneUpdate in the
    leader frame (x right, y forward): entities ``leader``, ``follower<i>`` (deleted while its
    pose is unknown), ``slots``, ``formation``, ``obstacles`` (as known) and ``safety``."""
    stamp = Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)

    def entity(eid: str, **parts: Any) -> SceneEntity:
        return SceneEntity(timestamp=stamp, frame_id="leader", id=eid, **parts)

    rings = [LinePrimitive(type=LinePrimitiveLineType.LineLoop, thickness=0.01, points=_circle(0.0, 0.0, r, 0.01),
                           color=_rgba(RING_BLUE)) for r in WORKING_RING_M]
    entities = [entity("leader", cubes=[CubePrimitive(pose=_pose(0.0, 0.0, 0.11), size=Vector3(x=0.40, y=0.45, z=0.22),
                                                      color=_rgba(LEADER_BLUE))],
                       arrows=[ArrowPrimitive(pose=_pose(0.0, 0.1, 0.25, math.pi / 2), shaft_length=0.27,
                                              shaft_diameter=0.03, head_length=0.08, head_diameter=0.08,
                                              color=_rgba(LEADER_BLUE))],
                       lines=rings)]
    deletions = []
    known = np.all(np.isfinite(s.p_est), axis=1) & np.isfinite(s.a_est)
    for i in range(s.n):
        eid = f"follower{i + 1}"
        if not (known[i] and bool(s.tracked[i])):
            deletions.append(SceneEntityDeletion(timestamp=stamp, id=eid))
            continue
        x, y, a = float(s.p_est[i, 0]), float(s.p_est[i, 1]), float(s.a_est[i])
        rgb = follower_rgb(i)
        entities.append(entity(
            eid, cubes=[CubePrimitive(pose=_pose(x, y, 0.05, a), size=Vector3(x=0.25, y=0.15, z=0.10),
                                      color=_rgba((45, 45, 45))),
                        CubePrimitive(pose=_pose(x, y, 0.105, a), size=Vector3(x=0.12, y=0.08, z=0.01), color=_rgba(rgb))],
            arrows=[ArrowPrimitive(pose=_pose(x + 0.1 * math.cos(a), y + 0.1 * math.sin(a), 0.12, a), shaft_length=0.19,
                                   shaft_diameter=0.02, head_length=0.06, head_diameter=0.06, color=_rgba(rgb))],
            texts=[TextPrimitive(pose=_pose(x, y, 0.3), billboard=True, font_size=14.0, scale_invariant=True,
                                 color=_rgba(rgb), text=s.name(i))]))
    slots = np.asarray(s.slot_targets, dtype=np.float64).reshape(-1, 2)
    entities.append(entity("slots", spheres=[SpherePrimitive(pose=_pose(float(x), float(y), SLOT_Z_M),
                                                             size=Vector3(x=0.08, y=0.08, z=0.08), color=_rgba(SLOT_RED))
                                             for x, y in slots if math.isfinite(x) and math.isfinite(y)]))
    used = slots[np.asarray(s.assignment, dtype=np.intp)] if len(slots) else np.zeros((0, 2))
    order = np.argsort(np.arctan2(used[:, 1], used[:, 0]))
    polygon = np.vstack([[0.0, 0.0], used[order], [0.0, 0.0]])
    entities.append(entity("formation", lines=[LinePrimitive(
        type=LinePrimitiveLineType.LineStrip, thickness=0.012, color=_rgba(SLOT_RED),
        points=[Point3(x=float(x), y=float(y), z=0.015) for x, y in polygon if math.isfinite(x) and math.isfinite(y)])]))
    pts = np.asarray(s.obstacles, dtype=np.float64).reshape(-1, 2) if s.obstacles is not None else np.zeros((0, 2))
    entities.append(entity("obstacles", cubes=[CubePrimitive(pose=_pose(float(x), float(y), 0.03),
                                                             size=Vector3(x=0.03, y=0.03, z=0.03), color=_rgba(KNOWN_ORANGE))
                                               for x, y in pts]))
    active = s.safety_active if s.safety_active is not None else np.zeros(s.n, dtype=bool)
    entities.append(entity("safety", lines=[
        LinePrimitive(type=LinePrimitiveLineType.LineLoop, thickness=0.02, color=_rgba(SAFETY_RED),
                      points=_circle(float(s.p_est[i, 0]), float(s.p_est[i, 1]), FOLLOWER_RADIUS_M * 2, 0.01))
        for i in range(s.n) if bool(active[i]) and known[i]]))
    return SceneUpdate(deletions=deletions, entities=entities)


def _bind_line(host: str, port: int, exc: Exception) -> str:
    """The SDK's error (``... (os error 98)``) as one line for people."""
    text = str(exc)
    m = re.search(r"os error (\d+)", text)
    if m and int(m.group(1)) == 98:
        why = "the port is in use (another program serves there: stop it or give another port)"
    elif m and int(m.group(1)) == 99:
        why = "this machine has no such address (give one of its own, or 127.0.0.1)"
    elif "TLS" in text or "tls" in text:
        why = f"the TLS certificate or key is not usable ({text.split(':', 1)[-1].strip()})"
    else:
        why = text.removeprefix("FoxgloveError: ")
    return f"--foxglove {host}:{port}: cannot serve: {why}"


class FoxgloveLive:
    """A Foxglove WebSocket server for one session: subscribe ``on_tick`` to the loop,
    ``on_params`` to the parameter store and ``on_trial`` to the step tests (see the module
    docstring). ``tls``: (certificate, key), PEM; required off loopback."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, tls: tuple[bytes, bytes] | None = None,
                 frame_rate_hz: float = 10.0, start_ns: int | None = None, name: str = "omniformation",
                 params: Params | None = None, time_of: Callable[[TickState], float] | None = None) -> None:
        """``start_ns``: the session's start (a recording's, so both carry the same times);
        ``time_of``: a tick's session time (a replay's, from its recording) instead of the clock."""
        if tls is None and not is_loopback(host):
            raise FoxgloveRefused(f"--foxglove {host}:{port}: serving off this machine needs TLS: give"
                                  " --foxglove-tls-cert CERT.pem and --foxglove-tls-key KEY.pem (or serve on 127.0.0.1)")
        quiet_sdk()
        self.frame_rate_hz = frame_rate_hz
        self.start_ns = time.time_ns() if start_ns is None else start_ns
        self.context = foxglove.Context()
        self.channels: dict[str, foxglove.Channel] = {}
        for topic, schema in TOPIC_SCHEMA.items():
            if topic in PROTOBUF_TOPICS:  # Foxglove's own schema, from its package, as the recording
                sch = foxglove.Schema(name=schema, encoding="protobuf", data=schema_data(PROTOBUF_TOPICS[topic]))
                self.channels[topic] = foxglove.Channel(topic, schema=sch, message_encoding="protobuf",
                                                        context=self.context)
            else:
                sch = foxglove.Schema(name=schema, encoding="jsonschema", data=json.dumps(SCHEMAS[schema]).encode())
                self.channels[topic] = foxglove.Channel(topic, schema=sch, message_encoding="json", context=self.context)
        self.scene = SceneUpdateChannel(SCENE_TOPIC, context=self.context)
        self.log = LogChannel(LOG_TOPIC, context=self.context)
        try:
            self.server = foxglove.start_server(
                name=name, host=host, port=port, capabilities=[], supported_encodings=[], context=self.context,
                message_backlog_size=BACKLOG, tls_cert=tls[0] if tls else None, tls_key=tls[1] if tls else None)
        except RuntimeError as exc:
            raise FoxgloveRefused(_bind_line(host, port, exc)) from None
        self.host = host
        self.port = int(self.server.port)
        self.scheme = "wss" if tls else "ws"
        self._queue: queue.Queue[tuple[str, Any] | None] = queue.Queue(maxsize=MAX_WAITING)
        self._clock = SessionClock()
        self.time_of = time_of
        self._prev: TickState | None = None
        self._params = params
        self._last_frame_t = -math.inf
        self._last_scan_t = -math.inf
        self._last_params_t = 0.0  # the set at the start goes out at once (params0)
        self._handed = 0  # items queued
        self._served = 0  # items the thread is done with
        self.ticks = 0  # states served
        self.dropped = 0  # states the queue had no room for
        self.logged: dict[str, int] = {t: 0 for t in (*self.channels, SCENE_TOPIC, LOG_TOPIC)}  # messages per topic
        self._thread = threading.Thread(target=self._run, name="omniformation-foxglove", daemon=True)
        self._thread.start()
        if params is not None:
            self._put("params0", params)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"

    # -- what the loop, the store and the step tests hand over (never waits) ---------------
    def _put(self, kind: str, item: Any) -> None:
        try:
            self._queue.put_nowait((kind, item))
            self._handed += 1
        except queue.Full:
            self.dropped += 1

    def on_tick(self, s: TickState) -> None:
        self._put("tick", s)

    def on_params(self, p: Params, source: str, notices: tuple[Any, ...]) -> None:
        self._put("params", (p, source))

    def on_trial(self, trial: Any) -> None:
        self.on_trial_payload(trial.payload())

    def on_trial_payload(self, payload: dict[str, Any]) -> None:
        self._put("trial", payload)

    # -- the server's thread ---------------------------------------------------------------
    def _ns(self, t: float) -> int:
        return self.start_ns + max(0, int(round(t * 1e9)))

    def _log(self, topic: str, data: bytes, ns: int) -> None:
        self.channels[topic].log(data, log_time=ns)
        self.logged[topic] += 1

    def _json(self, topic: str, payload: Any, ns: int) -> None:
        if self.channels[topic].has_sinks():
            self._log(topic, json.dumps(payload, separators=(",", ":")).encode(), ns)

    def _event(self, t: float, kind: str, detail: str) -> None:
        ns = self._ns(t)
        self._json(EVENT_TOPIC, {"t": t, "kind": kind, "detail": detail}, ns)
        if self.log.has_sinks():
            level = LogLevel.Warning if kind in WARNING_KINDS and detail != "STOP released" else LogLevel.Info
            self.log.log(Log(timestamp=Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000), level=level,
                             message=f"{kind}: {detail}", name="omniformation"), log_time=ns)
            self.logged[LOG_TOPIC] += 1

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            kind, value = item
            try:
                if kind == "tick":
                    self._serve_tick(value)
                elif kind == "params0":
                    self._json(PARAMS_TOPIC, params_payload(value), self._ns(0.0))
                elif kind == "params":
                    p, source = value
                    if self._params is not None:
                        for what, detail in params_events(self._params, p, source):
                            self._event(self._clock.last, what, detail)
                    self._params = p
                    self._last_params_t = self._clock.last
                    self._json(PARAMS_TOPIC, params_payload(p), self._ns(self._clock.last))
                elif kind == "trial":
                    t = self._clock.last
                    self._json(TRIAL_TOPIC, jsonable(value), self._ns(t))
                    self._event(t, "trial", f"trial {value['number']}: {value['label']}, {value['status']}")
            except Exception:  # a view must never take the session down
                log.exception("Foxglove live: a %s could not be served", kind)
            self._served += 1

    def _serve_tick(self, s: TickState) -> None:
        t = self._clock(s.t) if self.time_of is None else self.time_of(s)
        ns = self._ns(t)
        self._json(TICK_TOPIC, tick_payload(s), ns)
        if self.channels[TF_TOPIC].has_sinks():
            self._log(TF_TOPIC, encode(TF_TOPIC, transforms_payload(s, ns)), ns)
        for kind, detail in tick_events(self._prev, s):
            self._event(t, kind, detail)
        self._prev = s
        if self._params is not None and not 0.0 <= t - self._last_params_t < PARAMS_EVERY_S:  # for clients that join later
            self._last_params_t = t
            self._json(PARAMS_TOPIC, params_payload(self._params), ns)
        if s.scan is not None and not 0.0 <= t - self._last_scan_t < 1.0 / SCAN_HZ - 1e-9:  # a replay may seek back
            self._last_scan_t = t
            if self.channels[SCAN_TOPIC].has_sinks():
                self._log(SCAN_TOPIC, encode(SCAN_TOPIC, scan_payload(s.scan, ns)), ns)
        if s.frame is not None and self.frame_rate_hz > 0 and \
                not 0.0 <= t - self._last_frame_t < 1.0 / self.frame_rate_hz - 1e-9:
            self._last_frame_t = t
            if self.channels[IMAGE_TOPIC].has_sinks():
                ok, buf = cv2.imencode(".jpg", np.asarray(s.frame), [cv2.IMWRITE_JPEG_QUALITY, 80])
                if ok:
                    self._log(IMAGE_TOPIC, encode(IMAGE_TOPIC, image_payload(ns, buf.tobytes())), ns)
        if self.scene.has_sinks():
            self.scene.log(scene_update(s, ns), log_time=ns)
            self.logged[SCENE_TOPIC] += 1
        self.ticks += 1

    def drain(self, timeout: float = 10.0) -> bool:
        """Wait until every state handed over so far is served (tests, the bench); whether it was."""
        deadline = time.monotonic() + timeout
        while self._served < self._handed:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.002)
        return True

    def close(self) -> None:
        """Serve what is queued (at most a few seconds), then stop the server."""
        _close_served(self._queue, self._thread, self.server)


def _close_served(q: queue.Queue[Any], thread: threading.Thread, server: Any) -> None:
    """End a serving thread (its queue's end mark, then at most a few seconds to serve what is
    queued) and stop its Foxglove server: the session's and the fleet's views alike."""
    try:
        q.put(None, timeout=2.0)
    except queue.Full:
        pass
    thread.join(5.0)
    server.stop()


FLEET_SCENE_TOPIC = "/fleet/scene"
FLEET_SCHEMA = {"type": "object", "description": "as in docs/fleet-protocol.md"}


def _xy_list(rows: Any) -> list[tuple[float, float]]:
    out = []
    for p in rows if isinstance(rows, list) else []:
        try:
            x, y = float(p[0]), float(p[1])
        except (TypeError, ValueError, IndexError):
            continue
        if math.isfinite(x) and math.isfinite(y):
            out.append((x, y))
    return out


def fleet_scene(topic: str, msg: dict[str, Any], ns: int) -> SceneUpdate | None:
    """The fleet page's 3D view as a SceneUpdate in the world frame: the arena's robots (in their
    markers' hues) and leaders from its truth; each leader's estimates (blue) and slots (red),
    placed through its pose. None for a message that draws nothing."""
    stamp = Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)
    if topic == "arena/truth":
        robots: list[Any] = msg["robots"] if isinstance(msg.get("robots"), list) else []
        hues: list[Any] = msg["hues_deg"] if isinstance(msg.get("hues_deg"), list) else []
        cubes, texts = [], []
        for r, pose in enumerate(robots):
            try:
                x, y, th = (float(v) for v in pose[:3])
            except (TypeError, ValueError):
                continue
            rgb = hue_rgb(float(hues[r])) if r < len(hues) and isinstance(hues[r], (int, float)) else (120, 120, 120)
            cubes.append(CubePrimitive(pose=_pose(x, y, 0.05, th), size=Vector3(x=0.25, y=0.15, z=0.10), color=_rgba(rgb)))
            texts.append(TextPrimitive(pose=_pose(x, y, 0.25), billboard=True, font_size=14.0, scale_invariant=True,
                                       color=_rgba(rgb), text=f"R{r + 1}"))
        leaders: dict[str, Any] = msg["leaders"] if isinstance(msg.get("leaders"), dict) else {}
        for lid, pose in leaders.items():
            xy = _xy_list([pose])
            if xy:
                cubes.append(CubePrimitive(pose=_pose(xy[0][0], xy[0][1], 0.15), size=Vector3(x=0.34, y=0.34, z=0.3),
                                           color=_rgba((40, 40, 40))))
                texts.append(TextPrimitive(pose=_pose(xy[0][0], xy[0][1], 0.45), billboard=True, font_size=14.0,
                                           scale_invariant=True, color=_rgba((40, 40, 40)), text=str(lid)))
        return SceneUpdate(entities=[SceneEntity(timestamp=stamp, frame_id="world", id="arena", cubes=cubes, texts=texts)])
    if topic.endswith("/state"):
        pose = msg.get("leader")
        try:
            lx, ly, lth = (float(v) for v in pose[:3]) if isinstance(pose, list) else (0.0, 0.0, math.pi / 2)
        except (TypeError, ValueError):
            return None
        phi = lth - math.pi / 2  # leader frame (x right, y forward) to world
        c, s_ = math.cos(phi), math.sin(phi)

        def world(points: list[tuple[float, float]], rgb: tuple[int, int, int], size: float) -> list[SpherePrimitive]:
            return [SpherePrimitive(pose=_pose(lx + c * x - s_ * y, ly + s_ * x + c * y, 0.12),
                                    size=Vector3(x=size, y=size, z=size), color=_rgba(rgb)) for x, y in points]

        lid = topic.split("/")[0]
        return SceneUpdate(entities=[SceneEntity(
            timestamp=stamp, frame_id="world", id=f"team/{lid}",
            spheres=world(_xy_list(msg.get("p_est")), (30, 90, 220), 0.1) + world(_xy_list(msg.get("p_d")), SLOT_RED, 0.08))])
    return None


class FoxgloveFleet:
    """`fleet --foxglove`: what the fleet page hears on the bus, served to Foxglove as the fleet
    recording holds it (a JSON channel per leader and kind, ``/fleet/<id>/state``, ...,
    ``/fleet/arena/truth``) plus ``/fleet/scene``. Called as the fleet recorder is (``write``),
    from the bus's threads: messages are queued (full: dropped and counted) and served by a
    thread of its own."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 tls: tuple[bytes, bytes] | None = None) -> None:
        if tls is None and not is_loopback(host):
            raise FoxgloveRefused(f"--foxglove {host}:{port}: serving off this machine needs TLS: give"
                                  " --foxglove-tls-cert CERT.pem and --foxglove-tls-key KEY.pem (or serve on 127.0.0.1)")
        quiet_sdk()
        self.context = foxglove.Context()
        self.schema = foxglove.Schema(name="omniformation.FleetMessage", encoding="jsonschema",
                                      data=json.dumps(FLEET_SCHEMA).encode())
        self.channels: dict[str, foxglove.Channel] = {}
        self.scene = SceneUpdateChannel(FLEET_SCENE_TOPIC, context=self.context)
        try:
            self.server = foxglove.start_server(
                name="omniformation fleet", host=host, port=port, capabilities=[], supported_encodings=[],
                context=self.context, message_backlog_size=BACKLOG, tls_cert=tls[0] if tls else None,
                tls_key=tls[1] if tls else None)
        except RuntimeError as exc:
            raise FoxgloveRefused(_bind_line(host, port, exc)) from None
        self.host, self.port, self.scheme = host, int(self.server.port), "wss" if tls else "ws"
        self._queue: queue.Queue[tuple[str, int, dict[str, Any]] | None] = queue.Queue(maxsize=4096)
        self.served = 0
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name="omniformation-foxglove-fleet", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"

    def write(self, topic: str, msg: dict[str, Any]) -> None:
        try:
            self._queue.put_nowait((topic, time.time_ns(), msg))
        except queue.Full:
            self.dropped += 1

    def status(self) -> str:
        lost = f", {self.dropped} dropped" if self.dropped else ""
        return f"Foxglove live at {self.url}: {self.served} messages{lost}"

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            topic, ns, msg = item
            try:
                channel = self.channels.get(topic)
                if channel is None:
                    channel = self.channels[topic] = foxglove.Channel(f"/fleet/{topic}", schema=self.schema,
                                                                      message_encoding="json", context=self.context)
                channel.log(json.dumps(msg, separators=(",", ":")).encode(), log_time=ns)
                scene = fleet_scene(topic, msg, ns) if self.scene.has_sinks() else None
                if scene is not None:
                    self.scene.log(scene, log_time=ns)
                self.served += 1
            except Exception:  # a message the bus let through must not end the view
                log.exception("Foxglove fleet: a %s message could not be served", topic)

    def close(self) -> None:
        _close_served(self._queue, self._thread, self.server)
