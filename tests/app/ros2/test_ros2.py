"""The service as a ROS 2 node and a ROS 2 base as its leader, on a real Zenoh router (a Python
session in router mode on loopback, as `rmw_zenohd` would be). The ROS side here is written
from rmw_zenoh's design document and docs/ros2.md only: keys, liveliness tokens, the
attachment's bytes; CDR decoded by rosbags."""

from __future__ import annotations

import dataclasses
import json
import math
import struct
import threading
import time
from typing import Any

import numpy as np
import pytest
import zenoh

from tests.helpers import main_cli, wait_for

SLOTS = np.array([[-0.4, -0.3], [0.4, -0.3]])


def _free_endpoint() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _session(mode: str, endpoint: str) -> Any:
    import zenoh

    where = "listen" if mode == "router" else "connect"
    return zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": mode, where: {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}})))


def _types() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


class RosSide:
    """A ROS 2 party from the design document: subscribes to ``0/<topic>/<dds type>/*`` and keeps
    (CDR message, sequence, timestamp ns, gid) per topic; publishes with an attachment."""

    def __init__(self, session: Any) -> None:
        self.session, self.ts = session, _types()
        self.got: dict[str, list[tuple[Any, int, int, bytes]]] = {}
        self._subs: list[Any] = []
        self._lock = threading.Lock()

    def listen(self, topic: str, ros_type: str) -> None:
        pkg, _, name = ros_type.split("/")
        key = f"0/{topic.strip('/')}/{pkg}::msg::dds_::{name}_/*"
        self.got[topic] = []

        def on(sample: Any) -> None:
            att = sample.attachment.to_bytes()
            assert len(att) == 33 and att[16] == 16, att  # int64, int64, length 16, 16-byte GID
            seq, stamp, _, gid = struct.unpack("<qqB16s", att)
            msg = self.ts.deserialize_cdr(sample.payload.to_bytes(), ros_type)
            with self._lock:
                self.got[topic].append((msg, seq, stamp, gid))

        self._subs.append(self.session.declare_subscriber(key, on))

    def put(self, topic: str, ros_type: str, msg: Any, seq: int = 1, raw: bytes | None = None) -> None:
        from app.backends.ros2 import type_hash  # the published hashes are checked in test_ros2_wire

        pkg, _, name = ros_type.split("/")
        key = f"0/{topic.strip('/')}/{pkg}::msg::dds_::{name}_/{type_hash(ros_type)}"
        payload = raw if raw is not None else bytes(self.ts.serialize_cdr(msg, ros_type))
        self.session.put(key, payload, attachment=struct.pack("<qqB", seq, time.time_ns(), 16) + b"\x07" * 16)

    def tokens(self) -> list[str]:
        return [str(r.ok.key_expr) for r in self.session.liveliness().get("@ros2_lv/0/**", timeout=2.0)
                if r.ok is not None]


@pytest.fixture(scope="module")
def rig():
    """Router; the emulated base (its own node); the loop with --leader ros2:/cmd_vel and the
    bridge with --ros2-control; a ROS party listening to /tf and /cmd_vel."""
    from app.backends.ros2 import Ros2Base, Ros2Node
    from app.live.loop import ServiceLoop
    from app.backends.world import Backends
    from app.params import Params, ParamsStore
    from app.ros2.base import EmulatedBase
    from app.ros2.bridge import Ros2Bridge
    from app.ros2.session import open_ros2_session

    endpoint = _free_endpoint()
    router = _session("router", endpoint)
    ros = RosSide(_session("client", endpoint))
    ros.listen("/tf", "tf2_msgs/msg/TFMessage")
    ros.listen("/cmd_vel", "geometry_msgs/msg/Twist")
    ros.listen("/omniformation/status", "std_msgs/msg/String")
    ros.listen("/omniformation/camera/compressed", "sensor_msgs/msg/CompressedImage")
    base_node = Ros2Node(open_ros2_session([endpoint]), "base")
    base = EmulatedBase(base_node)
    base.start()
    node = Ros2Node(open_ros2_session([endpoint]), "omniformation")
    leader = Ros2Base(node)
    store = ParamsStore(Params(n_followers=2, slots=SLOTS.copy(), leader_mode="straight", leader_speed_mps=0.08))
    loop = ServiceLoop(store, Backends(seed=5, initial_poses=(SLOTS.copy(), np.full(2, math.pi / 2)), leader=leader),
                       rate_hz=30.0)
    bridge = Ros2Bridge(node, store, allow_control=True, base_state=lambda: leader.link_state)
    states: list[Any] = []
    loop.subscribe(states.append)
    loop.subscribe(bridge.on_tick)
    from core.types import Commands

    leader.send(Commands(np.array([0.08]), np.array([0.0])))  # rolling when the loop starts: eq. 5 on its odometry
    wait_for(lambda: not leader.lost and leader.measured()[0][0] > 0.04, 20, "the base's odometry")
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    yield {"loop": loop, "store": store, "base": base, "leader": leader, "node": node, "bridge": bridge,
           "states": states, "ros": ros, "router": router}
    loop.stop()
    thread.join(30)
    bridge.close()
    base.close()
    for n in (node, base_node):
        n.close()
        n.session.close()
    ros.session.close()
    router.close()


def test_a_ros_subscriber_from_the_design_decodes_tf_and_cmd_vel(rig):
    ros, loop = rig["ros"], rig["loop"]
    wait_for(lambda: len(ros.got["/tf"]) >= 20 and len(ros.got["/cmd_vel"]) >= 20, 30, "/tf and /cmd_vel")
    tf, seqs, stamps, gids = zip(*list(ros.got["/tf"]))
    assert {tuple(t.child_frame_id for t in m.transforms) for m in tf} == {("leader", "follower_1", "follower_2")}
    assert all(m.transforms[0].header.frame_id == "world" for m in tf)
    assert len(set(gids)) == 1 and np.all(np.diff(seqs) == 1)
    assert abs(stamps[-1] - time.time_ns()) < 60e9
    last = loop.last
    x, y = last.leader[:2]
    moved = [m.transforms[0].transform.translation for m in tf]
    assert any(abs(t.x - x) < 0.2 and abs(t.y - y) < 0.2 for t in moved[-10:])
    cmd, seqs, _, _ = zip(*list(ros.got["/cmd_vel"]))
    assert {round(c.linear.x, 6) for c in cmd[-5:]} == {0.08} and all(c.angular.z == 0.0 for c in cmd)
    assert np.all(np.diff(seqs) == 1)
    tokens = ros.tokens()
    zid = str(rig["node"].session.info.zid())
    assert f"@ros2_lv/0/{zid}/0/0/NN/%/%/omniformation" in tokens
    mine = [t.split("/") for t in tokens if t.startswith(f"@ros2_lv/0/{zid}/0/") and "/NN/" not in t]
    assert {(p[5], p[9].replace("%", "/"), p[10]) for p in mine} >= {
        ("MP", "/tf", "tf2_msgs::msg::dds_::TFMessage_"), ("MP", "/cmd_vel", "geometry_msgs::msg::dds_::Twist_"),
        ("MS", "/odom", "nav_msgs::msg::dds_::Odometry_"), ("MP", "/omniformation/status", "std_msgs::msg::dds_::String_"),
        ("MS", "/omniformation/stop", "std_msgs::msg::dds_::Bool_")}
    assert all(p[11].startswith("RIHS01_") and len(p[11]) == 71 for p in mine)
    # the attachment's GID is XXH3-128 of the publisher's token (rmw_zenoh's Entity), low half first
    from core.xxh3 import xxh3_128

    tf_token = next("/".join(p) for p in mine if p[5] == "MP" and p[9] == "%tf")
    assert gids[0] == struct.pack("<QQ", *xxh3_128(tf_token.encode()))


def test_the_camera_goes_out_as_a_jpeg_compressed_image(rig):
    import cv2

    frame = np.zeros((48, 64, 3), np.uint8)
    frame[:, :32] = (0, 0, 255)  # BGR: the left half red
    rig["bridge"].publish(dataclasses.replace(rig["loop"].last, frame=frame))
    got = rig["ros"].got["/omniformation/camera/compressed"]
    wait_for(lambda: got, 10, "a camera image")
    m = got[-1][0]
    img = cv2.imdecode(np.asarray(m.data, dtype=np.uint8), cv2.IMREAD_COLOR)
    assert m.format == "jpeg" and m.header.frame_id == "camera" and img.shape == frame.shape
    assert img[:, :28, 2].mean() > 200 and img[:, 36:, 2].mean() < 50


def test_the_leader_on_an_emulated_ros_base_keeps_the_formation(rig):
    states, base = rig["states"], rig["base"]
    wait_for(lambda: len(states) >= 90, 60, "3 s of ticks")
    moving = [s for s in states[15:] if not s.stopped]
    err = np.concatenate([np.linalg.norm(s.p_true - s.p_d, axis=1) for s in moving])
    rms = float(np.sqrt(np.mean(err ** 2)))
    print(f"formation RMS with the leader on a ROS 2 base: {rms * 100:.2f} cm over {len(moving)} ticks")
    assert rms <= 0.02
    # the simulated leader moved as the base's odometry says, which moved as commanded
    assert base.state.followers[0][1] > 0.1 and abs(states[-1].leader[1] - base.state.followers[0][1]) < 0.05


def test_stop_brings_the_bases_command_to_zero_within_two_ticks(rig):
    store, base, states = rig["store"], rig["base"], rig["states"]
    wait_for(lambda: len(base.commands) > 5 and base.commands[-1][0] > 0, 30, "the base driven")
    n0 = len(base.commands)
    store.update("test", stop=True)
    wait_for(lambda: len(base.commands) >= n0 + 10, 30, "ten more commands")
    after = base.commands[n0:]
    first_zero = next(i for i, c in enumerate(after) if c == (0.0, 0.0))
    print(f"STOP: the base's command zero after {first_zero} more command(s)")
    assert first_zero <= 2 and all(c == (0.0, 0.0) for c in after[first_zero:])  # zero every tick until released
    assert states[-1].leader_waits == "STOP"
    store.update("test", stop=False, leader_hold=False)
    wait_for(lambda: base.commands[-1][0] > 0, 30, "driving again")


def test_a_paused_loop_tells_the_base_to_stand_every_tick(rig):
    store, base = rig["store"], rig["base"]
    wait_for(lambda: base.commands and base.commands[-1][0] > 0, 30, "the base driven")
    n0 = len(base.commands)
    store.update("test", paused=True)
    wait_for(lambda: len(base.commands) >= n0 + 10, 30, "ten more commands")
    after = base.commands[n0:]
    first_zero = next(i for i, c in enumerate(after) if c == (0.0, 0.0))
    assert first_zero <= 2 and all(c == (0.0, 0.0) for c in after[first_zero:])
    store.update("test", paused=False)
    wait_for(lambda: base.commands[-1][0] > 0, 30, "driving again")


def test_stop_and_goals_from_ros_take_the_pages_checks(rig):
    ros, store, bridge = rig["ros"], rig["store"], rig["bridge"]
    ts = ros.ts
    Bool = ts.types["std_msgs/msg/Bool"]
    ros.put("/omniformation/stop", "std_msgs/msg/Bool", Bool(data=True))
    wait_for(lambda: store.get().stop, 10, "STOP from ROS")
    header = ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                             frame_id="world")
    P = ts.types["geometry_msgs/msg/Pose"]
    pose = P(position=ts.types["geometry_msgs/msg/Point"](x=0.5, y=1.5, z=0.0),
             orientation=ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    far = P(position=ts.types["geometry_msgs/msg/Point"](x=1e6, y=0.0, z=0.0), orientation=pose.orientation)
    PS = ts.types["geometry_msgs/msg/PoseStamped"]
    refused = bridge.refused + len(bridge.events)
    ros.put("/omniformation/goal", "geometry_msgs/msg/PoseStamped", PS(header=header, pose=far), seq=1)
    wait_for(lambda: bridge.refused + len(bridge.events) > refused, 10, "the far goal refused")
    assert store.get().goal is None and store.get().leader_mode == "straight"
    ros.put("/omniformation/goal", "geometry_msgs/msg/PoseStamped", PS(header=header, pose=pose), seq=2)
    wait_for(lambda: store.get().leader_mode == "goal", 10, "goal mode from ROS")
    assert store.get().goal == (0.5, 1.5) and store.get().stop  # a goal does not release STOP
    ros.put("/omniformation/stop", "std_msgs/msg/Bool", Bool(data=False), seq=2)
    wait_for(lambda: not store.get().stop, 10, "the release from ROS")
    store.update("test", leader_mode="straight")


def test_malformed_messages_from_ros_are_counted_and_dropped(rig):
    ros, node, leader = rig["ros"], rig["node"], rig["leader"]
    dropped = node.dropped
    ros.put("/odom", "nav_msgs/msg/Odometry", None, raw=b"\x00\x01\x00\x00garbage")
    ros.put("/omniformation/stop", "std_msgs/msg/Bool", None, raw=b"\xff" * 3)
    ts = ros.ts
    nan = ts.types["geometry_msgs/msg/Vector3"](x=math.nan, y=0.0, z=0.0)
    odom = ts.types["nav_msgs/msg/Odometry"](
        header=ts.types["std_msgs/msg/Header"](stamp=ts.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0),
                                               frame_id="odom"), child_frame_id="base_link",
        pose=ts.types["geometry_msgs/msg/PoseWithCovariance"](pose=ts.types["geometry_msgs/msg/Pose"](
            position=ts.types["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            orientation=ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)), covariance=np.zeros(36)),
        twist=ts.types["geometry_msgs/msg/TwistWithCovariance"](twist=ts.types["geometry_msgs/msg/Twist"](
            linear=nan, angular=nan), covariance=np.zeros(36)))
    refused = sum(leader.refused.values())
    ros.put("/odom", "nav_msgs/msg/Odometry", odom)  # it decodes, but says NaN (and is not the base's): dropped
    wait_for(lambda: node.dropped >= dropped + 2 and sum(leader.refused.values()) >= refused + 1, 10,
             "two malformed messages and the NaN odometry counted")
    v, w = leader.measured()
    assert np.isfinite(v).all() and np.isfinite(w).all()
    assert not rig["store"].get().stop and not leader.lost


def test_no_odometry_for_half_a_second_stops_the_leader_and_says_so(rig):
    states, base = rig["states"], rig["base"]
    base.close()  # the base is gone: no more odometry
    wait_for(lambda: "no odometry for 0.5 s" in states[-1].link_state, 10, "the link state saying so")
    status = rig["ros"].got["/omniformation/status"]
    wait_for(lambda: "no odometry" in json.loads(status[-1][0].data)["leader_base"], 10, "the status saying so")
    k = len(states)
    wait_for(lambda: len(states) >= k + 10, 30, "ten more ticks")
    leader = np.array([s.leader[:2] for s in states[k:]])
    assert np.ptp(leader, axis=0).max() < 1e-9  # the leader counts as stopped
    from app.recording.writer import tick_events

    events = [e for a, b in zip(states, states[1:]) for e in tick_events(a, b)]
    assert any(kind == "link" and "no odometry" in text for kind, text in events)


@pytest.mark.parametrize("args, words", [
    (["run", "--ros2", "--ros2-domain", "233", "--zenoh-connect", "tcp/127.0.0.1:7447"], "233 is outside 0..232"),
    (["run", "--ros2", "--zenoh-connect", "tcp/127.0.0.1:7447", "--leader", "ros2:cmd_vel"], "fully qualified"),
    (["run", "--leader", "ros2:/cmd_vel"], "needs --ros2"),
    (["run", "--ros2"], "needs --zenoh-connect"),
    (["run", "--ros2", "--zenoh-connect", "tcp/10.1.2.3:7447", "--no-record"], "stays on this machine"),
    (["emulate-base", "--ros2", "--zenoh-connect", "CLOSED"], "no ROS 2 Zenoh router answers"),
    (["emulate-base", "--ros2", "--speed-scale", "-1"], "-1 is outside [0, 2]"),
    (["run", "--ros2", "--zenoh-connect", "tcp/127.0.0.1:7447", "--ros2-intruder-stop"], "goes with --leader ros2:"),
])
def test_bad_ros2_input_is_one_line_and_exit_2(args, words):
    args = [_free_endpoint() if a == "CLOSED" else a for a in args]
    out = main_cli(*args)
    assert out.returncode == 2, out
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0], out.stderr


def test_run_ros2_with_a_ros_base_as_the_leader_from_the_command_line():
    """`run --ros2 --leader ros2:/cmd_vel` beside an emulated base: the node is on the graph,
    the base is driven, and when the service ends the last command it sent is zero."""
    from app.backends.ros2 import Ros2Node
    from app.ros2.base import EmulatedBase
    from app.ros2.session import open_ros2_session
    from tests.helpers import serve_then_signal

    endpoint = _free_endpoint()
    router = _session("router", endpoint)
    ros = RosSide(_session("client", endpoint))
    ros.listen("/omniformation/followers", "geometry_msgs/msg/PoseArray")
    node = Ros2Node(open_ros2_session([endpoint]), "base")
    base = EmulatedBase(node)
    base.start()
    try:
        run = serve_then_signal("--feedback", "truth", "--followers", "2", "--port", "0", "--no-record", "--ros2",
                                "--zenoh-connect", endpoint, "--leader", "ros2:/cmd_vel",
                                until=lambda: len(ros.got["/omniformation/followers"]) >= 10
                                and any(v > 0 for v, _ in base.commands))
        assert run.returncode == 0, run.stderr
        assert "ROS 2 node /omniformation on domain 0" in run.startup + run.stdout
        wait_for(lambda: base.commands and base.commands[-1] == (0.0, 0.0), 10, "the last command zero")
        poses = ros.got["/omniformation/followers"][-1][0]
        assert poses.header.frame_id == "leader" and len(poses.poses) == 2
    finally:
        base.close()
        node.close()
        node.session.close()
        ros.session.close()
        router.close()


def test_a_base_another_node_commands_already_is_refused():
    """A robot is never commanded by two programs: a publisher on the base's topic on the graph
    (its MP token, as rmw_zenoh declares it) makes `run --leader ros2:` refuse in one line."""
    from app.backends.ros2 import type_hash

    endpoint = _free_endpoint()
    router = _session("router", endpoint)
    stranger = _session("client", endpoint)
    h = type_hash("geometry_msgs/msg/Twist")
    token = stranger.liveliness().declare_token(
        f"@ros2_lv/0/{stranger.info.zid()}/0/10/MP/%/%/teleop/%cmd_vel/geometry_msgs::msg::dds_::Twist_/{h}/::,10:,:,:,,")
    try:
        out = main_cli("run", "--feedback", "truth", "--port", "0", "--no-record", "--ros2", "--zenoh-connect", endpoint,
                       "--leader", "ros2:/cmd_vel")
        assert out.returncode == 2, out
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and "/teleop publish(es) on /cmd_vel already" in lines[0], out.stderr
    finally:
        token.undeclare()
        stranger.close()
        router.close()


def test_a_stamped_base_gets_twist_stamped(rig):
    from app.backends.ros2 import Ros2Base
    from core.types import Commands

    ros = rig["ros"]
    ros.listen("/stamped_cmd", "geometry_msgs/msg/TwistStamped")
    base = Ros2Base(rig["node"], "/stamped_cmd", stamped=True, odom_topic="/stamped_odom")
    wait_for(lambda: base._cmd.wanted, 10, "the subscriber matched")
    base.send(Commands(np.array([0.25]), np.array([-0.5])))
    got = ros.got["/stamped_cmd"]
    wait_for(lambda: got, 10, "a TwistStamped")
    m = got[-1][0]
    assert (m.twist.linear.x, m.twist.angular.z, m.header.frame_id) == (0.25, -0.5, "base_link")
    assert base.lost and "no odometry yet" in base.link_state


def test_eq5_compensates_the_leaders_odometry_not_its_command():
    """A base that slips (emulate-base's speed scale 0.5: it really moves half of what it is told,
    and its /odom says so): eq. 5's leader motion is the odometry's twist, not the command, and
    the team keeps its formation. When the odometry goes stale the loop falls back to the
    commanded twist and its link state says so."""
    from app.backends.ros2 import Ros2Base, Ros2Node
    from app.live.loop import ServiceLoop
    from app.backends.world import Backends
    from app.params import Params, ParamsStore
    from app.ros2.base import EmulatedBase
    from app.ros2.session import open_ros2_session

    endpoint = _free_endpoint()
    router = _session("router", endpoint)
    base_node = Ros2Node(open_ros2_session([endpoint]), "base")
    base = EmulatedBase(base_node, speed_scale=0.5)
    base.start()
    node = Ros2Node(open_ros2_session([endpoint]), "omniformation")
    leader = Ros2Base(node)
    store = ParamsStore(Params(n_followers=2, slots=SLOTS.copy(), leader_mode="straight", leader_speed_mps=0.2))
    loop = ServiceLoop(store, Backends(seed=7, initial_poses=(SLOTS.copy(), np.full(2, math.pi / 2)), leader=leader),
                       rate_hz=30.0)
    used: list[tuple[Any, tuple[tuple[float, float], str]]] = []
    loop.subscribe(lambda s: used.append((s, loop.leader_motion)))  # each tick's own compensation
    thread = threading.Thread(target=loop.run, daemon=True)
    try:
        from core.types import Commands

        leader.send(Commands(np.array([0.2]), np.array([0.0])))  # the base already rolling when the loop starts
        wait_for(lambda: not leader.lost and leader.measured()[0][0] > 0.05, 20, "the base's odometry")
        thread.start()
        wait_for(lambda: len(used) >= 75, 60, "2.5 s of ticks")
        steady = used[30:75]
        assert all(src == "odometry" for _, (_, src) in steady), {src for _, (_, src) in steady}
        v_used = np.array([m[0] for _, (m, _) in steady])
        v_cmd = np.array([s.leader_twist[0] for s, _ in steady])
        print(f"eq. 5's leader speed: {v_used.mean():.3f} m/s from /odom, {v_cmd.mean():.3f} m/s commanded")
        assert np.allclose(v_cmd, 0.2) and np.allclose(v_used, 0.1, atol=0.01)  # the slip, not the command
        err = np.concatenate([np.linalg.norm(s.p_true - s.p_d, axis=1) for s, _ in steady])
        rms = float(np.sqrt(np.mean(err ** 2)))
        print(f"formation RMS on a slipping base, eq. 5 on its odometry: {rms * 100:.2f} cm")
        assert rms <= 0.02  # on the commanded twist the followers run ahead of the leader: 13 cm
        base.close()  # no more odometry: eq. 5 falls back to the command, and says so
        wait_for(lambda: used[-1][1][1] == "command (no fresh odometry)", 10, "the fallback")
        s, ((v, _), _) = used[-1]
        assert v == s.leader_twist[0] and "eq. 5 on the commanded twist" in s.link_state
    finally:
        loop.stop()
        thread.join(30)
        base.close()
        for n in (node, base_node):
            n.close()
            n.session.close()
        router.close()


@pytest.mark.parametrize("change, why", [
    ({}, ""),
    ({"frame": "robot1/odom", "child": "robot1/base_footprint"}, ""),
    ({"v": 0.61}, "speed"),
    ({"w": -1.1}, "turn rate"),
    ({"v": math.inf}, "not finite"),
    ({"frame": "map"}, "frame"),
    ({"child": "evil"}, "frame"),
    ({"stamp_ns": 10**9}, "stamp age"),
    ({"stamp_ns": 10**12 - 10**6}, "stamp order"),
    ({"sequence": 7}, "sequence"),
    ({"v": 0.55}, "acceleration"),  # 0.1 -> 0.55 m/s in 20 ms: 20 m/s^2 allows 0.4
    ({"v": 0.45}, ""),
])
def test_odometry_is_judged_by_the_parameter_tables_limits(change, why):
    from app.backends.ros2 import odometry_refusal

    now = 10**12 + 10**7
    m = {"v": 0.1, "w": 0.1, "stamp_ns": 10**12 + 2 * 10**7, "frame": "odom", "child": "base_link", "sequence": 8}
    m.update(change)
    last = (0.1, 0.0, 10**12, 7)  # the believed publisher's message before: 20 ms earlier
    assert odometry_refusal(m["v"], m["w"], m["stamp_ns"], m["frame"], m["child"], m["sequence"], last, now) == why


def test_two_odom_publishers_before_one_is_chosen_means_none_is_believed(rig):
    """Two publishers' tokens on /odom2 (as rmw_zenoh declares them) and odometry from one: not
    believed, the link state names both; once one token is gone, the other's next message is the
    base's, and the one that comes back is not believed."""
    from app.backends.ros2 import Ros2Base, type_hash
    from core.xxh3 import xxh3_128

    ros = rig["ros"]
    base = Ros2Base(rig["node"], "/cmd2", odom_topic="/odom2")
    h = type_hash("nav_msgs/msg/Odometry")
    zid = ros.session.info.zid()

    def token(node: str) -> tuple[Any, bytes]:
        key = f"@ros2_lv/0/{zid}/0/10/MP/%/%/{node}/%odom2/nav_msgs::msg::dds_::Odometry_/{h}/::,10:,:,:,,"
        return ros.session.liveliness().declare_token(key), struct.pack("<QQ", *xxh3_128(key.encode()))

    ts = ros.ts
    T = ts.types

    def odom(seq: int, gid: bytes) -> None:
        ns = time.time_ns()
        m = T["nav_msgs/msg/Odometry"](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                            frame_id="odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)), covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
                linear=T["geometry_msgs/msg/Vector3"](x=0.1, y=0.0, z=0.0),
                angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)), covariance=np.zeros(36)))
        key = f"0/odom2/nav_msgs::msg::dds_::Odometry_/{h}"
        ros.session.put(key, bytes(ts.serialize_cdr(m, "nav_msgs/msg/Odometry")),
                        attachment=struct.pack("<qqB", seq, ns, 16) + gid)

    (ta, ga), (tb, gb) = token("base_a"), token("base_b")
    wait_for(lambda: "several publishers on /odom2 (/base_a, /base_b)" in base.link_state, 10, "both named")
    odom(1, ga)
    wait_for(lambda: base.refused.get("several publishers, none believed"), 10, "not believed")
    assert base.odometry == 0
    tb.undeclare()
    wait_for(lambda: "several" not in base.link_state, 10, "one publisher left")
    odom(2, ga)
    wait_for(lambda: base.odometry == 1, 10, "the base's odometry believed")
    tb, gb = token("base_b")
    wait_for(lambda: "not believed on /odom2: /base_b" in base.link_state, 10, "the newcomer named")
    odom(1, gb)
    wait_for(lambda: base.refused.get("another publisher"), 10, "the newcomer's odometry dropped")
    assert base.odometry == 1
    ta.undeclare()
    tb.undeclare()


def test_a_flood_of_publishers_costs_a_bounded_link_state_and_log(rig):
    """600 publishers without a token, 3 messages each, on a base's odometry topic: the link state
    names three and counts the rest, what is remembered is bounded, and the log gets a bounded
    number of lines (the process's rate-limited refusals)."""
    from app.backends.ros2 import NAMES_SHOWN, TRACKED_MAX, Ros2Base
    from app.refusals import REFUSALS

    ros = rig["ros"]
    base = Ros2Base(rig["node"], "/cmd3", odom_topic="/odom3")
    base._believed = b"\x01" * 16  # a base chosen already: every other GID is a stranger
    lines = REFUSALS.lines
    from app.backends.ros2 import ODOMETRY, header, msg, pose, twist, type_hash

    cov = np.zeros(36)
    odom = msg(ODOMETRY, header=header("odom"), child_frame_id="base_link",
               pose=msg("geometry_msgs/msg/PoseWithCovariance", pose=pose(0.0, 0.0, 0.0), covariance=cov),
               twist=msg("geometry_msgs/msg/TwistWithCovariance", twist=twist(0.0, 0.0), covariance=cov))
    raw = bytes(ros.ts.serialize_cdr(odom, ODOMETRY))

    key = f"0/odom3/nav_msgs::msg::dds_::Odometry_/{type_hash('nav_msgs/msg/Odometry')}"
    for i in range(600):
        for seq in (1, 2, 3):
            # blocking, not dropped, on a loaded machine: every one of them reaches the base's subscriber
            ros.session.put(key, raw, attachment=struct.pack("<qqB", seq, time.time_ns(), 16) + (i + 2).to_bytes(16, "little"),
                            congestion_control=zenoh.CongestionControl.BLOCK)
    wait_for(lambda: base.refused.get("no publisher on the graph", 0) >= 1800, 60, "every message judged")
    state = base.link_state
    print(f"600 unannounced publishers: link state of {len(state)} characters; {REFUSALS.lines - lines} log lines")
    assert state.count("GID ") == NAMES_SHOWN and " more" in state and len(state) < 400
    assert len(base._unannounced) <= 2 * TRACKED_MAX
    assert REFUSALS.lines - lines <= 20
