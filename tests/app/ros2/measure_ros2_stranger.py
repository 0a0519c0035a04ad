"""What a stranger on the ROS 2 router does to the team, measured (not a test; run it by hand):

    .venv/bin/python -m tests.app.ros2.measure_ros2_stranger

The loop (30 Hz, two followers, the leader straight at 0.08 m/s) on an emulated ROS 2 base, on a
real Zenoh router on loopback. Printed: the followers' mean |v| and |w| over 3 s without and with a
second /odom publisher (its own node and token, 50 Hz, saying 0.3 m/s and 1 rad/s), and the
seconds until a second /cmd_vel publisher (a token and Twists at 20 Hz) is named in the link state
(or that it was not within 10 s)."""

from __future__ import annotations

import math
import struct
import threading
import time
from typing import Any

import numpy as np

from core.xxh3 import xxh3_128

SLOTS = np.array([[-0.4, -0.3], [0.4, -0.3]])


def _free_endpoint() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _session(mode: str, endpoint: str) -> Any:
    import json

    import zenoh

    where = "listen" if mode == "router" else "connect"
    return zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": mode, where: {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}})))


def _stranger(session: Any, node: str, topic: str, ros_type: str, ts: Any) -> tuple[list[Any], bytes, str]:
    pkg, _, name = ros_type.split("/")
    dds, h = f"{pkg}::msg::dds_::{name}_", ts.hash_rihs01(ros_type)
    head = f"@ros2_lv/0/{session.info.zid()}/0"
    token = f"{head}/10/MP/%/%/{node}/{topic.replace('/', '%')}/{dds}/{h}/::,10:,:,:,,"
    tokens = [session.liveliness().declare_token(f"{head}/0/NN/%/%/{node}"), session.liveliness().declare_token(token)]
    return tokens, struct.pack("<QQ", *xxh3_128(token.encode())), f"0/{topic.strip('/')}/{dds}/{h}"


def _mean_commands(states: list[Any], seconds: float, rate_hz: float) -> tuple[float, float]:
    k = len(states)
    while len(states) < k + int(seconds * rate_hz):
        time.sleep(0.05)
    c = np.array([s.commands for s in states[k:k + int(seconds * rate_hz)]])
    return float(np.abs(c[:, :, 0]).mean()), float(np.abs(c[:, :, 1]).mean())


def main() -> None:
    from rosbags.typesys import Stores, get_typestore

    from app.backends.ros2 import Ros2Base, Ros2Node
    from app.backends.world import Backends
    from app.live.loop import ServiceLoop
    from app.params import Params, ParamsStore
    from app.ros2.base import EmulatedBase
    from app.ros2.session import open_ros2_session
    from core.types import Commands

    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    endpoint = _free_endpoint()
    router = _session("router", endpoint)
    stranger = _session("client", endpoint)
    base_node = Ros2Node(open_ros2_session([endpoint]), "base")
    base = EmulatedBase(base_node)
    base.start()
    node = Ros2Node(open_ros2_session([endpoint]), "omniformation")
    leader = Ros2Base(node)
    store = ParamsStore(Params(n_followers=2, slots=SLOTS.copy(), leader_mode="straight", leader_speed_mps=0.08))
    loop = ServiceLoop(store, Backends(seed=5, initial_poses=(SLOTS.copy(), np.full(2, math.pi / 2)), leader=leader),
                       rate_hz=30.0)
    states: list[Any] = []
    loop.subscribe(states.append)
    leader.send(Commands(np.array([0.08]), np.array([0.0])))
    while leader.lost:
        time.sleep(0.05)
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    stop = threading.Event()
    try:
        _mean_commands(states, 1.0, 30.0)  # settle
        v0, w0 = _mean_commands(states, 3.0, 30.0)
        tokens, gid, key = _stranger(stranger, "evil", "/odom", "nav_msgs/msg/Odometry", ts)

        def forge() -> None:
            seq = 0
            while not stop.is_set():
                seq += 1
                ns = time.time_ns()
                m = T["nav_msgs/msg/Odometry"](
                    header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                        sec=ns // 10**9, nanosec=ns % 10**9), frame_id="odom"), child_frame_id="base_link",
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](
                        position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
                        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
                        covariance=np.zeros(36)),
                    twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
                        linear=T["geometry_msgs/msg/Vector3"](x=0.3, y=0.0, z=0.0),
                        angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=1.0)), covariance=np.zeros(36)))
                stranger.put(key, bytes(ts.serialize_cdr(m, "nav_msgs/msg/Odometry")),
                             attachment=struct.pack("<qqB", seq, ns, 16) + gid)
                stop.wait(0.02)

        forger = threading.Thread(target=forge, daemon=True)
        forger.start()
        _mean_commands(states, 0.5, 30.0)
        v1, w1 = _mean_commands(states, 3.0, 30.0)
        stop.set()
        forger.join(5)
        for t in tokens:
            t.undeclare()
        print(f"followers' mean |v| {v0:.3f} -> {v1:.3f} m/s, mean |w| {w0:.3f} -> {w1:.3f} rad/s"
              " (without -> with a second /odom publisher)")
        tokens, gid, key = _stranger(stranger, "teleop", "/cmd_vel", "geometry_msgs/msg/Twist", ts)
        start = time.monotonic()
        twist = T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                             angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=2.0))
        seq, named = 0, math.nan
        while time.monotonic() - start < 10.0:
            seq += 1
            stranger.put(key, bytes(ts.serialize_cdr(twist, "geometry_msgs/msg/Twist")),
                         attachment=struct.pack("<qqB", seq, time.time_ns(), 16) + gid)
            if "teleop" in states[-1].link_state:
                named = time.monotonic() - start
                break
            time.sleep(0.05)
        print(f"a second /cmd_vel publisher named after {named:.2f} s" if math.isfinite(named)
              else "a second /cmd_vel publisher: not named within 10 s")
        for t in tokens:
            t.undeclare()
    finally:
        stop.set()
        loop.stop()
        thread.join(30)
        base.close()
        for n in (node, base_node):
            n.close()
            n.session.close()
        stranger.close()
        router.close()


if __name__ == "__main__":
    main()
