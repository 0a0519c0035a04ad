"""A stranger on the ROS 2 machines' Zenoh router, written from docs/ros2.md and rmw_zenoh's wire
format alone (keys, liveliness tokens, the 33-byte attachment; CDR from rosbags). It imports
nothing of the service: it starts `omniformation emulate-base --ros2` and `omniformation run --ros2
--leader ros2:/cmd_vel` as programs and watches what anyone on the router can see (the status
topic, /tf, the service's stderr and its recording). core.xxh3 stands in for any XXH3 library
(rmw_zenoh's GID is XXH3-128 of a token).

One router, one base and one service for the whole module; the checks run in file order."""

from __future__ import annotations

import json
import math
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from core.xxh3 import xxh3_128

ROOT = Path(__file__).resolve().parents[3]
DOMAIN = 0
QOS = "::,10:,:,:,,"


def _types() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


TS = _types()


def _open(mode: str, endpoint: str) -> Any:
    import zenoh

    where = "listen" if mode == "router" else "connect"
    return zenoh.open(zenoh.Config.from_json5(json.dumps({
        "mode": mode, where: {"endpoints": [endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}})))


def _wait(pred: Callable[[], object], what: str, seen: Callable[[], str] | None = None, timeout: float = 60.0) -> float:
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        if pred():
            return time.monotonic() - start
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}" + (f" (seen: {seen()})" if seen else ""))


def _dds(ros_type: str) -> str:
    pkg, _, name = ros_type.split("/")
    return f"{pkg}::msg::dds_::{name}_"


def _key(topic: str, ros_type: str) -> str:
    return f"{DOMAIN}/{topic.strip('/')}/{_dds(ros_type)}/{TS.hash_rihs01(ros_type)}"


class Program:
    """A command run as a program: its stdout and stderr lines as they come."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "app.cli", *args], cwd=ROOT, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.out: list[str] = []
        self.err: list[str] = []
        for stream, lines in ((self.proc.stdout, self.out), (self.proc.stderr, self.err)):
            threading.Thread(target=self._read, args=(stream, lines), daemon=True).start()

    @staticmethod
    def _read(stream: Any, lines: list[str]) -> None:
        for line in stream:
            lines.append(line.rstrip("\n"))

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(60)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(10)


class Stranger:
    """A ROS 2 node as rmw_zenoh makes one: its node token, a publisher's MP token and its GID
    (XXH3-128 of the token, low half first), and publications with the attachment (int64
    sequence, int64 source ns, 16, GID)."""

    def __init__(self, session: Any, node: str) -> None:
        self.session, self.node = session, node
        zid = str(session.info.zid())
        self.head = f"@ros2_lv/{DOMAIN}/{zid}/0"
        self.tokens = [session.liveliness().declare_token(f"{self.head}/0/NN/%/%/{node}")]
        self.sequence = 0
        self.sent = 0

    def advertise(self, topic: str, ros_type: str, entity: int = 10) -> bytes:
        token = (f"{self.head}/{entity}/MP/%/%/{self.node}/{topic.replace('/', '%')}/{_dds(ros_type)}/"
                 f"{TS.hash_rihs01(ros_type)}/{QOS}")
        self.tokens.append(self.session.liveliness().declare_token(token))
        lo, hi = xxh3_128(token.encode())
        return struct.pack("<QQ", lo, hi)

    def put(self, topic: str, ros_type: str, message: Any, gid: bytes | None, sequence: int | None = None) -> None:
        self.sequence += 1
        seq = self.sequence if sequence is None else sequence
        att = None if gid is None else struct.pack("<qqB", seq, time.time_ns(), 16) + gid
        self.session.put(_key(topic, ros_type), bytes(TS.serialize_cdr(message, ros_type)), attachment=att)
        self.sent += 1

    def close(self) -> None:
        for t in self.tokens:
            t.undeclare()


def odometry(v: float, w: float, frame: str = "odom", child: str = "base_link", ns: int | None = None) -> Any:
    T = TS.types
    ns = time.time_ns() if ns is None else ns
    return T["nav_msgs/msg/Odometry"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id=frame), child_frame_id=child,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)),
            covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](
            linear=T["geometry_msgs/msg/Vector3"](x=v, y=0.0, z=0.0), angular=T["geometry_msgs/msg/Vector3"](
                x=0.0, y=0.0, z=w)), covariance=np.zeros(36)))


class Watcher:
    """What anyone on the router sees: the service's status JSON, /tf's world -> leader (stamp s,
    x, y, yaw), the base's odometry attachments (its GID and sequence)."""

    def __init__(self, session: Any) -> None:
        self.status: list[dict[str, Any]] = []
        self.leader: list[tuple[float, float, float, float]] = []
        self.base: list[tuple[int, bytes]] = []
        self._subs = [
            session.declare_subscriber(f"{DOMAIN}/omniformation/status/*/*", self._on_status),
            session.declare_subscriber(f"{DOMAIN}/tf/*/*", self._on_tf),
            session.declare_subscriber(f"{DOMAIN}/odom/*/*", self._on_odom),
        ]

    def _on_status(self, sample: Any) -> None:
        self.status.append(json.loads(TS.deserialize_cdr(sample.payload.to_bytes(), "std_msgs/msg/String").data))

    def _on_tf(self, sample: Any) -> None:
        m = TS.deserialize_cdr(sample.payload.to_bytes(), "tf2_msgs/msg/TFMessage")
        for t in m.transforms:
            if t.header.frame_id == "world" and t.child_frame_id == "leader":
                q, p = t.transform.rotation, t.transform.translation
                stamp = t.header.stamp.sec + t.header.stamp.nanosec * 1e-9
                self.leader.append((stamp, p.x, p.y, 2 * math.atan2(q.z, q.w)))

    def _on_odom(self, sample: Any) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else b""
        if len(att) == 33:
            seq, _, _, gid = struct.unpack("<qqB16s", att)
            self.base.append((seq, gid))

    def link(self) -> str:
        return str(self.status[-1]["link"]) if self.status else ""

    def yaw_rate(self, since: int) -> float:
        """The leader's mean turn rate (rad/s) over /tf since index ``since``, from the stamps."""
        got = self.leader[since:]
        yaw = [y for _, _, _, y in got]
        unwrapped = [yaw[0]]
        for a in yaw[1:]:
            unwrapped.append(unwrapped[-1] + math.remainder(a - unwrapped[-1], 2 * math.pi))
        return (unwrapped[-1] - unwrapped[0]) / (got[-1][0] - got[0][0])


def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    endpoint = _free_endpoint()
    router = _open("router", endpoint)
    session = _open("client", endpoint)
    watch = Watcher(session)
    recording = tmp_path_factory.mktemp("rec") / "session.mcap"
    base = Program("emulate-base", "--ros2", "--zenoh-connect", endpoint, "--seconds", "600")
    _wait(lambda: any("ROS 2 base on domain 0" in x for x in base.out), "the base")
    service = Program("run", "--feedback", "truth", "--followers", "2", "--port", "0", "--record", str(recording),
                      "--ros2", "--ros2-control", "--ros2-intruder-stop", "--zenoh-connect", endpoint,
                      "--leader", "ros2:/cmd_vel")
    try:
        _wait(lambda: watch.link().endswith("leader base: ros2 /cmd_vel") and len(watch.leader) > 10,
              "the service driving the base", lambda: f"{watch.link()!r}; {service.err[-5:]}")
        yield {"endpoint": endpoint, "session": session, "watch": watch, "base": base, "service": service,
               "recording": recording}
    finally:
        service.stop()
        base.stop()
        session.close()
        router.close()


def _base_gid(watch: Watcher) -> bytes:
    """The GID on most of the last 20 odometry messages (the base's 50 Hz; a stranger's stopped)."""
    from collections import Counter

    n = len(watch.base)
    _wait(lambda: len(watch.base) >= n + 20, "the base's odometry")
    return Counter(g for _, g in watch.base[-20:]).most_common(1)[0][0]


def _lines(program: Program, words: str) -> list[str]:
    return [x for x in program.err if words in x]


def test_a_second_odom_publisher_is_named_once_and_not_believed(rig):
    """/evil, a node with its own MP token on /odom, says the base turns at 1 rad/s and drives at
    0.3 m/s (50 Hz, fresh stamps, proper frames): the service names it and the leader does not turn."""
    watch, service = rig["watch"], rig["service"]
    evil = Stranger(rig["session"], "evil")
    gid = evil.advertise("/odom", "nav_msgs/msg/Odometry")
    stop = threading.Event()

    def forge() -> None:
        while not stop.is_set():
            evil.put("/odom", "nav_msgs/msg/Odometry", odometry(0.3, 1.0), gid)
            stop.wait(0.02)

    thread = threading.Thread(target=forge, daemon=True)
    thread.start()
    try:
        named = _wait(lambda: "/evil" in watch.link(), "the stranger named on the status")
        k, n0 = len(watch.leader), evil.sent
        _wait(lambda: evil.sent >= n0 + 50 and len(watch.leader) >= k + 30
              and watch.leader[-1][0] - watch.leader[k][0] >= 1.0, "a second of /tf and 50 forged messages")
        rate = watch.yaw_rate(k)
    finally:
        stop.set()
        thread.join(5)
        evil.close()
    print(f"a second /odom publisher named after {named:.2f} s; the leader's turn rate meanwhile {rate:.3f} rad/s"
          f" ({evil.sent} forged messages)")
    assert abs(rate) < 0.2  # the real base goes (nearly) straight; believed, /evil would turn the leader at ~1 rad/s
    assert len(_lines(service, "another publisher on /odom (/evil)")) == 1


def test_odometry_without_an_attachment_or_absurd_or_stale_or_in_a_wrong_frame_is_dropped(rig):
    """Under the base's own GID (read off its attachments): v = 1e6 without an attachment, then with
    it v = 1e6 and 1e308, stamps from 1970, frames map and evil. The leader does not jump; each
    kind is said on stderr once, then counted (at most one line more)."""
    watch, service = rig["watch"], rig["service"]
    gid = _base_gid(watch)
    liar = Stranger(rig["session"], "liar")
    k = len(watch.leader)
    for _ in range(20):
        liar.put("/odom", "nav_msgs/msg/Odometry", odometry(1e6, 0.0), None)
    _wait(lambda: len(watch.leader) >= k + 15, "ticks after the unattached odometry")
    assert not _lines(service, "dropped: speed")  # dropped as malformed before anything judged it
    forged = [odometry(1e6, 0.0), odometry(1e308, 0.0), odometry(0.05, 0.0, ns=10**9),
              odometry(0.05, 0.0, frame="map"), odometry(0.05, 0.0, child="evil")]
    for _ in range(5):
        for m in forged:
            seq = max(q for q, g in watch.base[-20:] if g == gid) + 1
            liar.put("/odom", "nav_msgs/msg/Odometry", m, gid, sequence=seq)
    for words in ("dropped: speed", "dropped: stamp age", "dropped: frame"):
        _wait(lambda w=words: _lines(service, w), words)
    j = len(watch.leader)
    _wait(lambda: len(watch.leader) >= j + 10, "ticks after")
    liar.close()
    xs = [(x, y) for _, x, y, _ in watch.leader[k:]]
    jump = max(math.dist(a, b) for a, b in zip(xs, xs[1:]))
    print(f"the leader's largest step between two /tf messages meanwhile: {jump * 100:.2f} cm")
    assert jump < 0.05
    for words in ("dropped: speed", "dropped: stamp age", "dropped: frame"):  # 10 or 5 messages each: the first
        assert 1 <= len(_lines(service, words)) <= 2, (words, service.err)  # said, the rest at most one count line


def test_goals_with_a_nan_or_non_unit_orientation_are_refused(rig):
    T, service = TS.types, rig["service"]
    op = Stranger(rig["session"], "operator")
    gid = op.advertise("/omniformation/goal", "geometry_msgs/msg/PoseStamped")
    for q in ((0.0, 0.0, math.nan, 1.0), (0.0, 0.0, 0.0, 0.0)):
        goal = T["geometry_msgs/msg/PoseStamped"](
            header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="world"),
            pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.5, y=1.5, z=0.0),
                                             orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2],
                                                                                           w=q[3])))
        op.put("/omniformation/goal", "geometry_msgs/msg/PoseStamped", goal, gid)
    _wait(lambda: _lines(service, "goal refused: position or orientation not finite")
          and _lines(service, "goal refused: orientation not a unit quaternion"), "both goals refused")
    op.close()


def test_a_base_that_only_sends_implausible_odometry_counts_as_stopped(rig):
    watch, base = rig["watch"], rig["base"]
    gid = _base_gid(watch)
    seq = max(q for q, g in watch.base if g == gid)
    base.stop()  # the real base is gone; only lies under its GID come
    liar = Stranger(rig["session"], "liar2")
    stop = threading.Event()

    def lie() -> None:
        n = seq + 1000
        while not stop.is_set():
            n += 1
            liar.put("/odom", "nav_msgs/msg/Odometry", odometry(5.0, 0.0), gid, sequence=n)
            stop.wait(0.02)

    thread = threading.Thread(target=lie, daemon=True)
    thread.start()
    try:
        _wait(lambda: "no odometry for 0.5 s" in watch.link(), "the base counted as stale")
    finally:
        stop.set()
        thread.join(5)
        liar.close()


def test_a_second_cmd_vel_publisher_is_an_alarm_and_with_the_option_stop(rig):
    """/teleop appears on /cmd_vel after start and turns the base at 2 rad/s: the service names it
    (status, stderr once, the recording's events and alarm) and, started with
    --ros2-intruder-stop, STOPs."""
    watch, service = rig["watch"], rig["service"]
    teleop = Stranger(rig["session"], "teleop")
    gid = teleop.advertise("/cmd_vel", "geometry_msgs/msg/Twist")
    T = TS.types
    twist = T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                         angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=2.0))
    teleop.put("/cmd_vel", "geometry_msgs/msg/Twist", twist, gid)
    named = _wait(lambda: "/teleop" in watch.link(), "the intruder named")
    _wait(lambda: watch.status[-1]["stopped"], "STOP")
    print(f"a second /cmd_vel publisher named after {named:.2f} s: {watch.link()}")
    assert "exclusive command lost, /teleop" in watch.link()
    n = len(watch.status)
    while len(watch.status) < n + 60:  # two seconds of ticks more: the page's process judges them too (its alarm)
        teleop.put("/cmd_vel", "geometry_msgs/msg/Twist", twist, gid)
        time.sleep(0.05)
    teleop.close()
    assert service.stop() == 0
    assert len(_lines(service, "another publisher on /cmd_vel (/teleop)")) == 1
    from mcap.reader import make_reader

    with open(rig["recording"], "rb") as f:
        events = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/omniformation/events"])]
    kinds = [(e["kind"], e["detail"]) for e in events]
    assert any(k == "link" and "/evil" in d for k, d in kinds)
    assert any(k == "link" and "/teleop" in d for k, d in kinds)
    assert any(k == "alarm" and "/teleop" in d for k, d in kinds), kinds
    assert any(k == "stop" for k, _ in kinds)
