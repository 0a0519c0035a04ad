"""Foxglove live (docs/foxglove.md), tested by a client written from Foxglove's WebSocket
protocol spec, not from the SDK: subprotocol foxglove.sdk.v1 / foxglove.websocket.v1, JSON
``serverInfo`` and ``advertise``, the client's ``subscribe``, binary Message Data frames (opcode
0x01, u32 subscription id, u64 timestamp, payload, little endian). Every message is decoded with
Foxglove's published schemas (foxglove-schemas-protobuf) or checked against the JSON Schema the
channel advertises."""

from __future__ import annotations

import base64
import datetime
import importlib
import json
import ssl
import struct
import threading
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.sync.client import connect

from app.live.config import DEFAULT_CONFIG, load_service_config
from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import MAX_FOLLOWERS, Params, ParamsStore
from tests.helpers import main_cli, wait_for

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
RECORDING_TOPICS = {"/omniformation/tick", "/tf", "/camera/image", "/scan", "/omniformation/events",
                    "/omniformation/params", "/omniformation/trials"}


class SpecClient:
    """A Foxglove WebSocket client from the protocol spec: it keeps the server's info, the
    channels advertised, status messages, and every Message Data frame per channel."""

    def __init__(self, url: str, ssl_context: ssl.SSLContext | None = None) -> None:
        self.ws = connect(url, subprotocols=SUBPROTOCOLS, ssl=ssl_context, open_timeout=10)
        assert self.ws.subprotocol in SUBPROTOCOLS
        self.info: dict[str, Any] = {}
        self.channels: dict[int, dict[str, Any]] = {}
        self.status: list[dict[str, Any]] = []
        self.data: dict[int, list[tuple[int, bytes]]] = defaultdict(list)  # channel id -> (timestamp, payload)
        self._channel_of: dict[int, int] = {}  # subscription id -> channel id
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        try:
            for frame in self.ws:
                if isinstance(frame, bytes):
                    assert frame[0] == 0x01, frame[:1]  # Message Data
                    sub, ts = struct.unpack_from("<IQ", frame, 1)
                    with self._lock:
                        self.data[self._channel_of[sub]].append((ts, frame[13:]))
                    continue
                msg = json.loads(frame)
                with self._lock:
                    if msg["op"] == "serverInfo":
                        self.info = msg
                    elif msg["op"] == "advertise":
                        self.channels.update({c["id"]: c for c in msg["channels"]})
                    elif msg["op"] == "status":
                        self.status.append(msg)
        except ConnectionClosed:
            return

    def subscribe_all(self) -> None:
        wait_for(lambda: self.info and self.channels, what="serverInfo and advertise")
        with self._lock:
            subs = [{"id": 100 + k, "channelId": cid} for k, cid in enumerate(sorted(self.channels))]
            self._channel_of.update({s["id"]: s["channelId"] for s in subs})
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def by_topic(self) -> dict[str, list[tuple[int, bytes]]]:
        with self._lock:
            return {c["topic"]: list(self.data.get(cid, [])) for cid, c in self.channels.items()}

    def close(self) -> None:
        self.ws.close()
        self._thread.join(5.0)


def _official_class(schema_name: str) -> Any:
    """foxglove.SceneUpdate -> the class Foxglove publishes in foxglove-schemas-protobuf."""
    package, _, name = schema_name.partition(".")
    assert package == "foxglove", schema_name
    return getattr(importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2"), name)


_JSON_TYPES = {"object": dict, "array": list, "string": str, "boolean": bool, "integer": int,
               "number": (int, float), "null": type(None)}


def _check_json(value: Any, schema: dict[str, Any], where: str = "") -> None:
    """The JSON Schema keywords the channels use (type, properties, items), checked."""
    kinds = schema.get("type")
    if kinds is not None:
        kinds = [kinds] if isinstance(kinds, str) else kinds
        ok = any(isinstance(value, _JSON_TYPES[k]) and not (k in ("integer", "number") and isinstance(value, bool))
                 for k in kinds)
        assert ok, f"{where}: {value!r:.80} is not {kinds}"
    if isinstance(value, dict):
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                _check_json(value[key], sub, f"{where}.{key}")
    if isinstance(value, list) and "items" in schema:
        for k, item in enumerate(value):
            _check_json(item, schema["items"], f"{where}[{k}]")


def decode(channel: dict[str, Any], payload: bytes) -> Any:
    """A message by its channel's advertisement: protobuf with the official class (and the
    schema sent is a FileDescriptorSet naming it), JSON against the advertised JSON Schema."""
    if channel["encoding"] == "protobuf":
        from google.protobuf import descriptor_pb2

        fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        assert any(channel["schemaName"] == f"{f.package}.{m.name}" for f in fds.file for m in f.message_type)
        return _official_class(channel["schemaName"]).FromString(payload)
    assert channel["encoding"] == "json" and channel.get("schemaEncoding", "jsonschema") == "jsonschema"
    msg = json.loads(payload)
    _check_json(msg, json.loads(channel["schema"]), channel["topic"])
    return msg


@pytest.fixture
def loop_and_live():
    from app.services.foxglove_live import FoxgloveLive

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    store = ParamsStore(Params(n_followers=3))
    loop = ServiceLoop(store, Backends(seed=2, camera=config.camera()), rate_hz=30.0)
    live = FoxgloveLive("127.0.0.1", 0, params=store.get())
    loop.subscribe(live.on_tick)
    store.subscribe(live.on_params)
    try:
        yield loop, store, live
    finally:
        live.close()


def test_a_client_from_the_spec_decodes_every_channel_and_gets_a_scene_per_tick(loop_and_live):
    loop, store, live = loop_and_live
    client = SpecClient(live.url)
    try:
        client.subscribe_all()
        topics = {c["topic"] for c in client.channels.values()}
        assert topics == RECORDING_TOPICS | {"/omniformation/scene", "/omniformation/log"}
        # the subscription is in place once the tick channel delivers: only then count
        for _ in range(200):
            loop.tick()
            live.drain()
            if client.by_topic()["/omniformation/tick"]:
                break
        wait_for(lambda: client.by_topic()["/omniformation/tick"], what="a first tick")
        by_topic = {c["topic"]: c for c in client.channels.values()}
        first = loop.tick_count  # the 45 ticks below, by their numbers (earlier ones may still be on their way)

        def ours(got: dict[str, list[Any]]) -> list[Any]:
            return [(ts, p) for ts, p in got["/omniformation/tick"] if decode(by_topic["/omniformation/tick"], p)["tick"] >= first]

        for k in range(45):
            if k == 10:
                store.update("browser:1", k_f1=0.12)  # an event and a parameter set
            loop.tick()
        assert live.drain() and live.dropped == 0
        def every_tick_and_its_scene() -> bool:
            got = client.by_topic()
            scene_times = {ts for ts, _ in got["/omniformation/scene"]}
            ticks = ours(got)
            return len(ticks) >= 45 and all(ts in scene_times for ts, _ in ticks)

        wait_for(every_tick_and_its_scene, what="every tick and a scene at its time")
        got = client.by_topic()
        decoded: dict[str, list[Any]] = {t: [decode(by_topic[t], p) for _, p in msgs] for t, msgs in got.items()}
        ticks = ours(got)
        assert len(ticks) == 45
        scene_times = {ts for ts, _ in got["/omniformation/scene"]}
        tf_times = {ts for ts, _ in got["/tf"]}
        for ts, _ in ticks:  # every tick: its scene and its transforms, at the tick's time
            assert ts in scene_times and ts in tf_times
        assert [decode(by_topic["/omniformation/tick"], p)["tick"] for _, p in ticks] == list(range(first, first + 45))
        assert any(e["kind"] == "gain" and "k_f1 0.1 -> 0.12" in e["detail"] for e in decoded["/omniformation/events"])
        assert [m.message for m in decoded["/omniformation/log"]] == \
               [f"{e['kind']}: {e['detail']}" for e in decoded["/omniformation/events"]]  # the event log, for Foxglove
        assert decoded["/omniformation/params"][-1]["gains"]["k_f1"] == pytest.approx(0.12)
        jpeg = decoded["/camera/image"]
        assert len(jpeg) >= 10 and all(m.format == "jpeg" and m.data[:2] == b"\xff\xd8" for m in jpeg)
        scene = decoded["/omniformation/scene"][-1]
        ids = {e.id for e in scene.entities} | {d.id for d in scene.deletions}
        assert {"leader", "slots", "formation", "obstacles", "safety", "follower1", "follower2", "follower3"} <= ids
        assert all(e.frame_id == "leader" for e in scene.entities)
        assert len(next(e for e in scene.entities if e.id == "slots").spheres) == 3
        frames = {f for m in decoded["/tf"] for t in m.transforms for f in (t.parent_frame_id, t.child_frame_id)}
        assert "leader" in frames  # the scene's frame is placed by /tf
        followers = [e for e in scene.entities if e.id.startswith("follower")]
        for e in followers:  # each in its page colour (core.camera.render.looks.follower_rgb)
            from core.camera.render.looks import follower_rgb

            r, g, b = follower_rgb(int(e.id.removeprefix("follower")) - 1)
            marker = e.cubes[1].color
            assert (round(marker.r * 255), round(marker.g * 255), round(marker.b * 255)) == (r, g, b)
    finally:
        client.close()


def test_a_client_can_neither_publish_nor_set_parameters(loop_and_live):
    """View-only: the server offers no capability; a client's advertise, message data and
    parameter writes change nothing, and the session goes on being served."""
    loop, store, live = loop_and_live
    client = SpecClient(live.url)
    try:
        client.subscribe_all()
        caps = set(client.info.get("capabilities", []))
        assert not caps & {"clientPublish", "parameters", "parametersSubscribe", "services", "connectionGraph", "assets"}
        before = store.get()
        client.ws.send(json.dumps({"op": "advertise", "channels": [
            {"id": 1, "topic": "/omniformation/params", "encoding": "json", "schemaName": "omniformation.Params"}]}))
        client.ws.send(b"\x01" + struct.pack("<I", 1) + json.dumps({"stop": True, "k_f1": 9.0}).encode())
        client.ws.send(json.dumps({"op": "setParameters", "parameters": [{"name": "k_f1", "value": 9.0}], "id": "x"}))
        client.ws.send(json.dumps({"op": "getParameters", "parameterNames": [], "id": "y"}))
        for _ in range(200):
            loop.tick()
            live.drain()
            if client.by_topic()["/omniformation/tick"]:
                break
        wait_for(lambda: client.by_topic()["/omniformation/tick"], what="ticks still served")
        after = store.get()
        assert after.version == before.version and after.gains == before.gains and not after.stop
        wait_for(lambda: len([m for m in client.status if m["level"] == 2]) >= 2, what="refusals said")
    finally:
        client.close()


def _self_signed(tmp_path: Path) -> tuple[Path, Path]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID
    import ipaddress

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    now = datetime.datetime.now(datetime.UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - datetime.timedelta(minutes=1))
            .not_valid_after(now + datetime.timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False)
            .sign(key, hashes.SHA256()))
    cert_path, key_path = tmp_path / "cert.pem", tmp_path / "key.pem"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    return cert_path, key_path


def test_with_tls_only_wss_is_served(tmp_path):
    from app.services.foxglove_live import FoxgloveLive

    cert, key = _self_signed(tmp_path)
    live = FoxgloveLive("127.0.0.1", 0, tls=(cert.read_bytes(), key.read_bytes()))
    try:
        assert live.url.startswith("wss://")
        ctx = ssl.create_default_context(cafile=str(cert))
        client = SpecClient(live.url, ctx)
        wait_for(lambda: client.info.get("op") == "serverInfo", what="serverInfo over TLS")
        client.close()
        with pytest.raises((OSError, WebSocketException, TimeoutError)):  # a plain ws:// client is not served
            connect(live.url.replace("wss://", "ws://"), subprotocols=SUBPROTOCOLS, open_timeout=3).recv(timeout=3)
    finally:
        live.close()


def test_bad_foxglove_arguments_are_one_line_and_exit_2(tmp_path):
    from app.services.foxglove_live import FoxgloveLive

    cert, key = _self_signed(tmp_path)
    taken = FoxgloveLive("127.0.0.1", 0)
    try:
        cases = [
            (("--foxglove", "0.0.0.0:0"), "needs TLS"),
            (("--foxglove", "192.0.2.7:8765"), "needs TLS"),
            (("--foxglove", "8765:x"), "not [HOST:]PORT"),
            (("--foxglove", "70000"), "0..65535"),
            (("--foxglove", "0", "--foxglove-tls-cert", str(cert)), "go together"),
            (("--foxglove-tls-cert", str(cert), "--foxglove-tls-key", str(key)), "go with --foxglove"),
            (("--foxglove", "0", "--foxglove-tls-cert", str(tmp_path / "none.pem"), "--foxglove-tls-key", str(key)),
             "cannot be read"),
            (("--foxglove", "0", "--foxglove-tls-cert", str(tmp_path), "--foxglove-tls-key", str(key)), "cannot be read"),
            (("--foxglove", f"127.0.0.1:{taken.port}"), "in use"),
        ]
        (tmp_path / "junk.pem").write_text("-----BEGIN CERTIFICATE-----\nnot a certificate\n")
        cases.append((("--foxglove", "0", "--foxglove-tls-cert", str(tmp_path / "junk.pem"), "--foxglove-tls-key",
                       str(tmp_path / "junk.pem")), "TLS certificate or key is not usable"))
        for extra, words in cases:
            r = main_cli("run", "--feedback", "truth", "--no-record", "--port", "0", *extra)
            assert r.returncode == 2, (extra, r.stdout, r.stderr)
            lines = r.stderr.strip().splitlines()
            assert len(lines) == 1 and words in lines[0] and "Traceback" not in r.stderr, (extra, r.stderr)
        r = main_cli("replay", "no-such.mcap", "--port", "0", "--foxglove", "0.0.0.0:0")  # checked before the file
        assert r.returncode == 2 and "needs TLS" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    finally:
        taken.close()


def test_replay_serves_the_recordings_ticks_at_their_recorded_times(tmp_path):
    """`replay --foxglove`: the ticks shown go out with the recording's own times."""
    from app.recording.reader import read_recording
    from app.recording.writer import Recorder
    from app.services.replay import ReplayService
    from app.cli.foxglove_args import serve_replay
    import argparse

    store = ParamsStore(Params(n_followers=2))
    loop = ServiceLoop(store, Backends(seed=1), rate_hz=30.0)
    rec = Recorder(tmp_path / "r.mcap", {"scenario": "test"}, store.get())
    loop.subscribe(rec.on_tick)
    for _ in range(30):
        loop.tick()
    rec.close()
    back = read_recording(tmp_path / "r.mcap")
    args = argparse.Namespace(foxglove=("127.0.0.1", 0), foxglove_tls_cert=None, foxglove_tls_key=None)
    live = serve_replay(args, back)
    assert live is not None
    svc = ReplayService(back, host="127.0.0.1", port=0)
    svc.listeners.append(live.on_tick)
    client = SpecClient(live.url)
    try:
        client.subscribe_all()
        wait_for(lambda: len(client.channels) == 9, what="advertise")
        for _ in range(100):
            svc.seek(0)
            live.drain()
            if client.by_topic()["/omniformation/tick"]:
                break
        for k in range(1, 30):
            svc.seek(k)
        live.drain()
        wait_for(lambda: any(json.loads(p)["tick"] == int(back.tick_numbers[-1])
                             for _, p in client.by_topic()["/omniformation/tick"]), what="the last tick")
        start_ns = int(back.metadata["start_ns"])
        recorded = {int(n): start_ns + int(round(t * 1e9)) for n, t in zip(back.tick_numbers, back.t)}
        for ts, p in client.by_topic()["/omniformation/tick"]:
            assert ts == recorded[json.loads(p)["tick"]]
    finally:
        client.close()
        svc.close()
        live.close()
        back.close()


def test_the_scene_shows_known_obstacles_and_safety_rings():
    """The scene from a state with obstacles and a held-back follower: the points and a ring."""
    from app.services.foxglove_live import scene_update
    from app.tick import TickState
    from core.types import Gains
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

    n = 2
    s = TickState(tick=1, t=0.1, leader=np.zeros(3), leader_twist=(0.0, 0.0), followers_world=np.zeros((n, 3)),
                  p_est=np.array([[0.5, -0.5], [np.nan, np.nan]]), a_est=np.array([1.5, np.nan]),
                  tracked=np.array([True, False]), p_true=np.zeros((n, 2)), a_true=np.zeros(n),
                  p_d=np.zeros((n, 2)), slot_targets=np.array([[0.5, -0.5], [-0.5, -0.5]]),
                  assignment=np.array([0, 1]), commands=np.zeros((n, 2)), a_err=np.zeros(n), v_lyap=np.zeros(n),
                  gains=Gains(), params_version=0, stopped=False, paused=False, link_state="sim", rate_hz=30.0,
                  safety_active=np.array([True, False]), obstacles=np.array([[1.0, 1.0], [1.1, 1.0], [1.2, 1.0]]))
    msg = SceneUpdate.FromString(scene_update(s, 123).encode())
    entities = {e.id: e for e in msg.entities}
    assert len(entities["obstacles"].cubes) == 3
    assert len(entities["safety"].lines) == 1  # the held-back follower, known; not the lost one
    assert "follower1" in entities and [d.id for d in msg.deletions] == ["follower2"]
    assert entities["leader"].timestamp.nanos == 123


def test_fleet_messages_and_the_arena_scene_reach_a_spec_client():
    """`fleet --foxglove`: each bus message on the fleet recording's channel, and the arena's
    truth and each leader's view as a foxglove.SceneUpdate in the world frame."""
    from app.services.foxglove_live import FoxgloveFleet

    truth = {"t": 1.0, "leaders": {"L1": [0.0, 0.0, 1.57]}, "robots": [[0.5, -0.5, 1.5], [-0.5, -0.5, 1.6]],
             "velocities": [[0, 0], [0, 0]], "hues_deg": [0.0, 120.0], "owners": ["L1", "L1"]}
    state = {"t": 1.0, "leader": [0.0, 0.0, 1.57], "p_est": [[0.5, -0.5], [None, None]], "p_d": [[0.5, -0.5], [-0.5, -0.5]],
             "tracked": [True, False]}
    live = FoxgloveFleet("127.0.0.1", 0)
    client = SpecClient(live.url)
    try:
        live.write("arena/truth", truth)
        live.write("L1/state", state)
        wait_for(lambda: {"/fleet/arena/truth", "/fleet/L1/state", "/fleet/scene"}
                 <= {c["topic"] for c in client.channels.values()}, what="the fleet's channels")
        client.subscribe_all()

        def served() -> bool:
            live.write("arena/truth", truth)
            live.write("L1/state", state)
            got = client.by_topic()
            return all(got.get(t) for t in ("/fleet/arena/truth", "/fleet/L1/state")) and len(got["/fleet/scene"]) >= 2

        wait_for(served, what="fleet messages and scenes")
        by_topic = {c["topic"]: c for c in client.channels.values()}
        got = client.by_topic()
        decoded = {t: [decode(by_topic[t], p) for _, p in msgs] for t, msgs in got.items()}
        assert decoded["/fleet/arena/truth"][-1]["robots"] == truth["robots"]
        entities = {e.id: e for m in decoded["/fleet/scene"] for e in m.entities}
        assert len(entities["arena"].cubes) == 3 and entities["arena"].frame_id == "world"  # 2 robots, 1 leader
        assert len(entities["team/L1"].spheres) == 3  # one estimate known, two slots
    finally:
        client.close()
        live.close()
    r = main_cli("fleet", "--fleet", "f1", "--port", "0", "--foxglove", "0.0.0.0:0")
    assert r.returncode == 2 and "needs TLS" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_the_layout_reads_only_what_the_server_offers():
    """docs/foxglove-layout.json: every topic its panels and its user script read is one Foxglove
    live advertises (or the script's own output), and its panels are the 3D, image, plot and log."""
    from app.services.foxglove_live import LOG_TOPIC, SCENE_TOPIC
    from tests.helpers import ROOT

    layout = json.loads((ROOT / "docs" / "foxglove-layout.json").read_text())
    offered = RECORDING_TOPICS | {SCENE_TOPIC, LOG_TOPIC}
    scripts = layout["userNodes"].values()
    outputs = {line.split('"')[1] for s in scripts for line in s["sourceCode"].splitlines()
               if line.startswith("export const output")}
    for s in scripts:
        inputs = next(line for line in s["sourceCode"].splitlines() if line.startswith("export const inputs"))
        assert set(json.loads(inputs.split("=", 1)[1].strip().rstrip(";"))) <= offered
    read = set()
    for config in layout["configById"].values():
        read |= set(config.get("topics", {}))
        read |= {config["imageMode"]["imageTopic"]} if config.get("imageMode", {}).get("imageTopic") else set()
        read |= {p["value"].split(".")[0] for p in config.get("paths", [])}
        read |= {config["topicToRender"]} if "topicToRender" in config else set()
    assert read and read <= offered | outputs, read - offered - outputs
    kinds = {pid.split("!")[0] for pid in layout["configById"]}
    assert kinds == {"3D", "Image", "Plot", "RosOut"}

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])
