"""A ROS 2 node on rmw_zenoh's wire format, and a leader base that is a ROS 2 robot.

The wire (keys, liveliness tokens, attachment) is core.rmw_zenoh's, from rmw_zenoh's design
document; payloads are CDR from ``rosbags`` (its ROS 2 Jazzy type store). The type hashes
(RIHS01, REP-2011) are rosbags' ``hash_rihs01``: SHA-256 over the canonical JSON of each
type's description, made from the ROS 2 Jazzy message definitions rosbags ships.
tests/core/test_rmw_zenoh.py checks it against hashes published elsewhere: std_msgs/msg/String
(rmw_zenoh's docs/design.md) and geometry_msgs/msg/Twist, sensor_msgs/msg/Imu, MagneticField,
FluidPressure and Temperature (keys of running rmw_zenoh systems).

This node is a Zenoh *client* of the ROS 2 machines' router (``rmw_zenohd`` or ``zenohd``): it
listens on nothing and reaches the ROS nodes through the router (docs/ros2.md). A message
from ROS that does not decode, carries a bad attachment or non-finite numbers is counted
(``Ros2Node.dropped``) and dropped.
"""

from __future__ import annotations

import math
import re
import sys
import threading
import time
from collections.abc import Callable
from functools import lru_cache
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from core.rmw_zenoh import ADMIN_SPACE, PUBLISHER, SUBSCRIPTION, EntityToken, NodeName, check_topic, data_key, \
    decode_attachment, encode_attachment, entity_gid, parse_entity_token
from core.bounds import LEADER_SPEED, LEADER_TURN
from core.types import GAIN_BOUNDS, BoolArray, Commands, FloatArray

if TYPE_CHECKING:
    import zenoh

ODOM_TIMEOUT_S = 0.5  # no odometry for this long: the base counts as stopped (and says so)
TWIST, TWIST_STAMPED, ODOMETRY = "geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped", "nav_msgs/msg/Odometry"


@lru_cache(maxsize=1)
def typestore() -> Any:
    """rosbags' ROS 2 Jazzy types (CDR and the type descriptions)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


@lru_cache(maxsize=64)
def type_hash(ros_type: str) -> str:
    """The REP-2011 hash of a ROS 2 Jazzy type (``RIHS01_…``), else ValueError (unknown type)."""
    ts = typestore()
    if ros_type not in ts.types:
        raise ValueError(f"ROS 2 type {ros_type!r}: unknown (ROS 2 Jazzy's types, e.g. geometry_msgs/msg/Twist)")
    return str(ts.hash_rihs01(ros_type))


def msg(ros_type: str, **fields: Any) -> Any:
    """A rosbags message object of ``ros_type``."""
    return typestore().types[ros_type](**fields)


def stamp(ns: int | None = None) -> Any:
    ns = time.time_ns() if ns is None else ns
    return msg("builtin_interfaces/msg/Time", sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def header(frame_id: str, ns: int | None = None) -> Any:
    return msg("std_msgs/msg/Header", stamp=stamp(ns), frame_id=frame_id)


def vector3(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Any:
    return msg("geometry_msgs/msg/Vector3", x=float(x), y=float(y), z=float(z))


def quaternion_yaw(yaw: float) -> Any:
    return msg("geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))


def yaw_of(q: Any) -> float:
    """The heading (rad, about z) of a quaternion message."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def pose(x: float, y: float, yaw: float) -> Any:
    return msg("geometry_msgs/msg/Pose", position=msg("geometry_msgs/msg/Point", x=float(x), y=float(y), z=0.0),
               orientation=quaternion_yaw(yaw))


def twist(v: float, w: float) -> Any:
    return msg(TWIST, linear=vector3(v), angular=vector3(0.0, 0.0, w))


class Ros2Publisher:
    """One publisher: its data key, its ``MP`` token, its GID and running sequence number."""

    def __init__(self, node: Ros2Node, entity_id: int, topic: str, ros_type: str) -> None:
        h = type_hash(ros_type)
        self.ros_type = ros_type
        self.key = data_key(node.name.domain, topic, ros_type, h)
        self.token_key = node.name.entity_token(entity_id, PUBLISHER, topic, ros_type, h)
        self.gid = entity_gid(self.token_key)
        self.sequence = 0
        self._pub = node.session.declare_publisher(self.key)
        self._token = node.session.liveliness().declare_token(self.token_key)
        self.sent = 0

    @property
    def wanted(self) -> bool:
        """A subscriber anywhere matches (Zenoh's matching status): else nothing need be made or sent."""
        try:
            status = self._pub.matching_status  # a MatchingStatus (its stub says bool)
            return bool(getattr(status, "matching", status))
        except Exception:  # noqa: BLE001 - a closed session: nothing to send to
            return False

    def put(self, message: Any) -> None:
        """Serialise (CDR) and publish with rmw_zenoh's attachment."""
        self.put_cdr(bytes(typestore().serialize_cdr(message, self.ros_type)))

    def put_cdr(self, payload: bytes) -> None:
        self.sequence += 1
        self._pub.put(payload, attachment=encode_attachment(self.sequence, time.time_ns(), self.gid))
        self.sent += 1

    def close(self) -> None:
        for x in (self._token, self._pub):
            x = cast(Any, x)
            try:
                x.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closed already
                pass


class Ros2Node:
    """A ROS 2 node: its ``NN`` token, publishers and subscriptions (their tokens), and a count of
    messages from ROS that were dropped as malformed."""

    def __init__(self, session: zenoh.Session, name: str, domain: int = 0, namespace: str = "/") -> None:
        self.session = session
        self.name = NodeName(domain, str(session.info.zid()), name, namespace)
        self._token = session.liveliness().declare_token(self.name.node_token())
        self._next_id = 9  # entity ids within the node: the first is 10, as in rmw_zenoh's design document
        self._entities: list[Any] = []
        self._lock = threading.Lock()
        self.dropped = 0
        self.received = 0

    def _entity_id(self) -> int:
        self._next_id += 1
        return self._next_id

    def publisher(self, topic: str, ros_type: str) -> Ros2Publisher:
        pub = Ros2Publisher(self, self._entity_id(), check_topic(topic), ros_type)
        self._entities.append(pub)
        return pub

    def subscribe(self, topic: str, ros_type: str, on_message: Callable[..., None],
                  with_attachment: bool = False) -> None:
        """Call ``on_message(msg)`` (``on_message(msg, attachment)`` with ``with_attachment``: its
        (sequence, source ns, GID)) with each decoded message. A publication without rmw_zenoh's
        attachment or with a malformed one, a message that does not decode, or ``on_message``
        raising ValueError: counted in ``dropped``, nothing else."""
        h = type_hash(ros_type)
        key = data_key(self.name.domain, check_topic(topic), ros_type, h)
        token = self.session.liveliness().declare_token(
            self.name.entity_token(self._entity_id(), SUBSCRIPTION, topic, ros_type, h))
        ts = typestore()

        def handler(sample: Any) -> None:
            try:
                if sample.attachment is None:  # every rmw_zenoh publication carries one (design.md)
                    raise ValueError("no attachment")
                attachment = decode_attachment(sample.attachment.to_bytes())
                message = ts.deserialize_cdr(sample.payload.to_bytes(), ros_type)
                on_message(message, attachment) if with_attachment else on_message(message)
            except Exception:  # noqa: BLE001 - bytes from the network: whatever fails to decode is dropped
                with self._lock:
                    self.dropped += 1
                return
            with self._lock:
                self.received += 1

        self._entities.extend([self.session.declare_subscriber(key, handler), token])

    def watch_graph(self, on_token: Callable[[EntityToken, bool], None]) -> None:
        """Call ``on_token(token, alive)`` for every publisher's and subscription's liveliness
        token of this node's domain on the graph now and as each comes (True) or goes (False)."""
        import zenoh

        domain = self.name.domain

        def handler(sample: Any) -> None:
            token = parse_entity_token(str(sample.key_expr), domain)
            if token is not None:
                on_token(token, sample.kind == zenoh.SampleKind.PUT)

        self._entities.append(self.session.liveliness().declare_subscriber(f"{ADMIN_SPACE}/{domain}/**", handler,
                                                                          history=True))

    def watch_data(self, topic: str, on_sample: Callable[[bytes | None], None]) -> None:
        """Call ``on_sample(attachment bytes or None)`` for every publication on ``topic``, of any
        type, ours included (a plain Zenoh subscriber: no token, ROS tools do not see it)."""
        key = f"{self.name.domain}/{check_topic(topic).strip('/')}/*/*"

        def handler(sample: Any) -> None:
            on_sample(None if sample.attachment is None else sample.attachment.to_bytes())

        self._entities.append(self.session.declare_subscriber(key, handler))

    def close(self) -> None:
        for e in reversed(self._entities):
            try:
                e.close() if isinstance(e, Ros2Publisher) else e.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closed already
                pass
        try:
            self._token.undeclare()
        except Exception:  # noqa: BLE001
            pass


def publishers_of(session: zenoh.Session, domain: int, topic: str, timeout_s: float = 1.0) -> list[str]:
    """The nodes (``namespace/name``) with a publisher on ``topic`` in ``domain`` now, from the
    graph's liveliness tokens (rmw_zenoh's ``MP`` tokens: kind at part 5, node at 8, topic at 9)."""
    from core.rmw_zenoh import ADMIN_SPACE, mangle

    found = []
    for reply in session.liveliness().get(f"{ADMIN_SPACE}/{domain}/**", timeout=timeout_s):
        ok = getattr(reply, "ok", None)
        parts = str(ok.key_expr).split("/") if ok is not None else []
        if len(parts) >= 10 and parts[5] == PUBLISHER and parts[9] == mangle(topic):
            found.append(f"{parts[7].replace('%', '/').rstrip('/')}/{parts[8]}")
    return found


def finite_twist(t: Any) -> tuple[float, float]:
    """(v, w) of a Twist, else ValueError (non-finite numbers are a malformed message)."""
    v, w = float(t.linear.x), float(t.angular.z)
    if not (math.isfinite(v) and math.isfinite(w)):
        raise ValueError("non-finite twist")
    return v, w


# What a leader base's odometry may say (docs/ros2.md, "What the service believes of /odom"): twice
# what the leader may be told (the parameter table's speed and turn-rate bounds: a base overshoots
# a little, never by double), no faster change than the table lets any robot be commanded, a stamp
# within ODOM_STAMP_AGE_S of this machine's clock and later than the one before, an odom frame.
ODOM_SPEED_MAX = 2.0 * LEADER_SPEED.hi  # m/s
ODOM_TURN_MAX = 2.0 * math.radians(LEADER_TURN.hi)  # rad/s
ODOM_ACCEL_MAX = GAIN_BOUNDS["accel_v_max"].hi  # m/s^2
ODOM_TURN_ACCEL_MAX = GAIN_BOUNDS["accel_w_max"].hi  # rad/s^2
ODOM_MIN_DT_S = 0.01  # the acceleration is judged over at least this long (stamps closer than that: 100 Hz)
ODOM_STAMP_AGE_S = 1.0  # the base's clock and ours agree within this (NTP or chrony between machines)
ODOM_FRAME = re.compile(r"([A-Za-z0-9_]+[/_])?odom")
ODOM_CHILD = re.compile(r"([A-Za-z0-9_]+[/_])?base_(link|footprint)")
UNANNOUNCED_AFTER = 3  # a GID on no token of the graph is named after this many of its messages
STRANGER_HOLD_S = 5.0  # a publisher without a token is named this long after its last message
TRACKED_MAX = 256  # publishers remembered per topic, with and without a token (a flood forgets the oldest)
NAMES_SHOWN = 3  # names in the link state per topic; the rest counted


def _names(names: list[str]) -> str:
    more = len(names) - NAMES_SHOWN
    return ", ".join(names[:NAMES_SHOWN]) + (f" and {more} more" if more > 0 else "")


def odometry_refusal(v: float, w: float, stamp_ns: int, frame: str, child: str, sequence: int,
                     last: tuple[float, float, int, int] | None, now_ns: int) -> str:
    """Why an Odometry from the believed base is not plausible ("" when it is): ``last`` is the
    (v, w, stamp ns, sequence) of that publisher's message before, ``now_ns`` this machine's clock."""
    if not (math.isfinite(v) and math.isfinite(w)):
        return "not finite"
    if ODOM_FRAME.fullmatch(frame) is None or ODOM_CHILD.fullmatch(child) is None:
        return "frame"
    if abs(v) > ODOM_SPEED_MAX:
        return "speed"
    if abs(w) > ODOM_TURN_MAX:
        return "turn rate"
    if abs(now_ns - stamp_ns) > ODOM_STAMP_AGE_S * 1e9:
        return "stamp age"
    if last is not None:
        if sequence <= last[3]:
            return "sequence"
        if stamp_ns <= last[2]:
            return "stamp order"
        dt = max((stamp_ns - last[2]) * 1e-9, ODOM_MIN_DT_S)
        if abs(v - last[0]) > ODOM_ACCEL_MAX * dt or abs(w - last[1]) > ODOM_TURN_ACCEL_MAX * dt:
            return "acceleration"
    return ""


def _say(text: str) -> None:
    print(f"omniformation: ROS 2: {text}", file=sys.stderr, flush=True)


class Ros2Base:
    """The leader's base as a ROS 2 robot, a FollowerLink of one: each tick's leader (v, w) goes
    out on its command topic (Twist, or TwistStamped), its odometry (nav_msgs/msg/Odometry on
    ``odom_topic``) is what it measured. No believable odometry for ODOM_TIMEOUT_S: it is
    ``lost``, measured (0, 0) (the leader counts as stopped), and its state says so.

    Only the base is believed: the odometry of the one publisher on ``odom_topic`` the graph (its
    liveliness token, whose hash is the GID its attachment carries) showed alone when its first
    plausible message came; every other publisher there is named (the link state, stderr once)
    and not heard. Each message is judged by :func:`odometry_refusal`; what fails is dropped and
    counted. Another publisher on the command topic is named too, as an alarm (the link state
    says our exclusive command is lost), and told to :meth:`on_intrusion`'s listener once."""

    n = 1

    def __init__(self, node: Ros2Node, cmd_topic: str = "/cmd_vel", stamped: bool = False,
                 odom_topic: str = "/odom", clock: Callable[[], float] = time.monotonic,
                 wall_ns: Callable[[], int] = time.time_ns) -> None:
        self.node = node
        self.cmd_topic, self.odom_topic, self.stamped = cmd_topic, odom_topic, stamped
        self._cmd = node.publisher(cmd_topic, TWIST_STAMPED if stamped else TWIST)
        self._clock, self._wall_ns = clock, wall_ns
        self._lock = threading.Lock()
        self._odom: tuple[float, float, float] | None = None  # (v, w, monotonic time it came)
        self.odom_pose: tuple[float, float, float] | None = None
        self.odometry = 0
        self.refused: dict[str, int] = {}  # odometry dropped, by why
        self._on_intruder: Callable[[str], None] | None = None
        self._intrusions: list[str] = []  # every intruder on the command topic named so far
        self._tokens: dict[str, dict[bytes, EntityToken]] = {cmd_topic: {}, odom_topic: {}}  # live MP tokens by GID
        self._believed: bytes | None = None  # the base's /odom publisher (its GID), once chosen
        self._last: tuple[float, float, int, int] | None = None  # the believed publisher's last message
        self._unannounced: dict[tuple[str, bytes], list[float]] = {}  # (topic, GID) -> [messages, last seen]
        self._named: dict[tuple[str, str], None] = {}  # (topic, name) said on stderr already (ordered)
        node.watch_graph(self._on_token)
        node.watch_data(cmd_topic, self._on_cmd_sample)
        node.subscribe(odom_topic, ODOMETRY, self._on_odom, with_attachment=True)

    # -- the graph ----------------------------------------------------------------------
    def _on_token(self, token: EntityToken, alive: bool) -> None:
        if token.kind != PUBLISHER or token.topic not in self._tokens or token.key == self._cmd.token_key:
            return
        with self._lock:
            if alive:
                tokens = self._tokens[token.topic]
                tokens[token.gid] = token
                while len(tokens) > TRACKED_MAX:  # a flood of tokens: the oldest forgotten (never the base's)
                    oldest = next(g for g in tokens if g != self._believed)
                    del tokens[oldest]
            else:
                self._tokens[token.topic].pop(token.gid, None)
        if alive:
            self._check_strangers()

    def _on_cmd_sample(self, attachment: bytes | None) -> None:
        try:
            gid = decode_attachment(attachment)[2] if attachment is not None else b""
        except ValueError:
            gid = b""
        if gid == self._cmd.gid:
            return  # ours
        with self._lock:
            known = gid in self._tokens[self.cmd_topic]
        if not known:
            self._count_unannounced(self.cmd_topic, gid)
        self._check_strangers()

    def _count_unannounced(self, topic: str, gid: bytes) -> None:
        with self._lock:
            seen = self._unannounced.pop((topic, gid), [0, 0.0])  # re-inserted: the oldest first
            seen[0] += 1
            seen[1] = self._clock()
            self._unannounced[(topic, gid)] = seen
            while len(self._unannounced) > 2 * TRACKED_MAX:
                del self._unannounced[next(iter(self._unannounced))]

    def strangers(self) -> dict[str, list[str]]:
        """Per topic (command, odometry), the publishers named now besides ours and the base's."""
        now = self._clock()
        with self._lock:
            out: dict[str, list[str]] = {self.cmd_topic: [], self.odom_topic: []}
            for topic, tokens in self._tokens.items():
                for gid, token in tokens.items():
                    if topic == self.cmd_topic or (self._believed is not None and gid != self._believed):
                        out[topic].append(token.node)
            for (topic, gid), (count, last) in self._unannounced.items():
                if count >= UNANNOUNCED_AFTER and now - last <= STRANGER_HOLD_S and gid != self._believed:
                    out[topic].append(f"GID {gid.hex()[:12] or 'none'} (no token on the graph)")
        return {topic: sorted(set(names)) for topic, names in out.items()}

    def _check_strangers(self) -> None:
        """Name each new stranger once on stderr (through the rate-limited refusals: a flood of
        ever new names adds a bounded number of lines); a new one on the command topic is an
        intrusion, told to :meth:`on_intrusion`'s listener."""
        from app.refusals import refuse

        for topic, names in self.strangers().items():
            for name in names:
                with self._lock:
                    if (topic, name) in self._named:
                        continue
                    self._named[(topic, name)] = None
                    while len(self._named) > 16 * TRACKED_MAX:
                        del self._named[next(iter(self._named))]
                if topic == self.cmd_topic:
                    text = f"{name} publishes on {topic} too: the base may obey it, not us"
                    refuse(f"ros2: another publisher on {topic}", name, "the base may obey it, not us")
                    with self._lock:
                        self._intrusions.append(text)
                        del self._intrusions[:-TRACKED_MAX]
                        tell = self._on_intruder
                    if tell is not None:
                        tell(text)
                else:
                    refuse(f"ros2: another publisher on {topic}", name, "not believed (the base's is)")

    def on_intrusion(self, tell: Callable[[str], None]) -> None:
        """Call ``tell(text)`` for each publisher on the command topic besides us: those named
        already, then each as it is named."""
        with self._lock:
            self._on_intruder = tell
            told = list(self._intrusions)
        for text in told:
            tell(text)

    # -- odometry -----------------------------------------------------------------------
    def _refuse(self, why: str, gid: bytes, detail: str = "") -> None:
        """One odometry message dropped: counted (the link detail) and said through the process's
        rate-limited refusals (app.refusals: the first per publisher and kind, then counts)."""
        from app.refusals import refuse

        with self._lock:
            self.refused[why] = self.refused.get(why, 0) + 1
        refuse(f"ros2: {self.odom_topic} dropped: {why}", f"GID {gid.hex()[:12] or 'none'}",
               detail or "not the base's odometry")

    def _on_odom(self, m: Any, attachment: tuple[int, int, bytes]) -> None:
        sequence, _, gid = attachment
        with self._lock:
            tokens = dict(self._tokens[self.odom_topic])
            believed = self._believed
        if gid not in tokens:
            if believed is None or gid != believed:
                self._count_unannounced(self.odom_topic, gid)
                self._refuse("no publisher on the graph", gid)
                self._check_strangers()
                return
        elif believed is None and len(tokens) > 1:
            self._refuse("several publishers, none believed", gid)
            return
        elif believed is not None and gid != believed:
            self._refuse("another publisher", gid, f"{tokens[gid].node} is not the base")
            self._check_strangers()
            return
        v, w = float(m.twist.twist.linear.x), float(m.twist.twist.angular.z)
        st = m.header.stamp
        stamp_ns = int(st.sec) * 1_000_000_000 + int(st.nanosec)
        p = m.pose.pose
        pose_xyw = (float(p.position.x), float(p.position.y), yaw_of(p.orientation))
        why = odometry_refusal(v, w, stamp_ns, str(m.header.frame_id), str(m.child_frame_id), sequence, self._last,
                               self._wall_ns())
        if why == "" and not all(math.isfinite(q) for q in pose_xyw):
            why = "not finite"
        if why not in ("sequence", "stamp order", "stamp age", "not finite"):
            self._last = (v, w, stamp_ns, sequence) if math.isfinite(v) and math.isfinite(w) else self._last
        if why:
            self._refuse(why, gid, f"v {v:g} m/s, w {w:g} rad/s, stamp {stamp_ns * 1e-9:.3f} s, frames"
                                   f" {str(m.header.frame_id)[:32]!r} -> {str(m.child_frame_id)[:32]!r}, sequence {sequence}")
            return
        with self._lock:
            if self._believed is None:
                self._believed = gid
                chosen = tokens[gid].node
            else:
                chosen = ""
            self._odom = (v, w, self._clock())
            self.odom_pose = pose_xyw
            self.odometry += 1
        if chosen:
            _say(f"the base's odometry: {chosen} on {self.odom_topic} (only it is believed)")
            self._check_strangers()

    @property
    def lost(self) -> bool:
        with self._lock:
            return self._odom is None or self._clock() - self._odom[2] > ODOM_TIMEOUT_S

    @property
    def link_state(self) -> str:
        """``ros2 TOPIC``, then (first: the page's alarm reads "lost" before any parenthesis) another
        publisher on the command topic, the odometry's state and the publishers not believed."""
        state = f"ros2 {self.cmd_topic}"
        strangers = self.strangers()
        if strangers[self.cmd_topic]:  # an alarm on the page ("lost"), an event in the recording
            state += f": exclusive command lost, {_names(strangers[self.cmd_topic])} publish(es) on {self.cmd_topic} too"
        if self._odom is None:
            state += ": no odometry yet"
        elif self.lost:
            state += f": no odometry for {ODOM_TIMEOUT_S:g} s"
        with self._lock:
            several = self._believed is None and len(self._tokens[self.odom_topic]) > 1
            several_names = sorted(t.node for t in self._tokens[self.odom_topic].values())
        if several:
            state += f" · several publishers on {self.odom_topic} ({_names(several_names)}): none believed"
        elif strangers[self.odom_topic]:
            state += f" · not believed on {self.odom_topic}: {_names(strangers[self.odom_topic])}"
        return state

    def send(self, commands: Commands) -> None:
        v, w = float(commands.v[0]), float(commands.w[0])
        if self.stamped:
            self._cmd.put(msg(TWIST_STAMPED, header=header("base_link"), twist=twist(v, w)))
        else:
            self._cmd.put(twist(v, w))

    def answering(self) -> BoolArray:
        return np.array([not self.lost])

    def measured(self) -> tuple[FloatArray, FloatArray]:
        with self._lock:
            odom = self._odom
        if odom is None or self.lost:
            return np.zeros(1), np.zeros(1)
        return np.array([odom[0]]), np.array([odom[1]])

    def detail(self) -> str:
        with self._lock:
            refused = sum(self.refused.values())
            kinds = ", ".join(f"{k} {n}" for k, n in sorted(self.refused.items()))
        return (f"leader base: {self.odometry} odometry messages, {self.node.dropped} malformed dropped,"
                f" {refused} not believed" + (f" ({kinds})" if kinds else ""))

    def close(self) -> None:
        try:
            self.send(Commands.zeros(1))  # the base stops when we go
        except Exception:  # noqa: BLE001 - the session may be gone
            pass
