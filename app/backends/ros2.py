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
import threading
import time
from collections.abc import Callable
from functools import lru_cache
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from core.rmw_zenoh import PUBLISHER, SUBSCRIPTION, NodeName, check_topic, data_key, decode_attachment, \
    encode_attachment, entity_gid
from core.types import BoolArray, Commands, FloatArray

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

    def subscribe(self, topic: str, ros_type: str, on_message: Callable[[Any], None]) -> None:
        """Call ``on_message(msg)`` with each decoded message; a message that does not decode, a bad
        attachment, or ``on_message`` raising ValueError: counted in ``dropped``, nothing else."""
        h = type_hash(ros_type)
        key = data_key(self.name.domain, check_topic(topic), ros_type, h)
        token = self.session.liveliness().declare_token(
            self.name.entity_token(self._entity_id(), SUBSCRIPTION, topic, ros_type, h))
        ts = typestore()

        def handler(sample: Any) -> None:
            try:
                if sample.attachment is not None:
                    decode_attachment(sample.attachment.to_bytes())
                on_message(ts.deserialize_cdr(sample.payload.to_bytes(), ros_type))
            except Exception:  # noqa: BLE001 - bytes from the network: whatever fails to decode is dropped
                with self._lock:
                    self.dropped += 1
                return
            with self._lock:
                self.received += 1

        self._entities.extend([self.session.declare_subscriber(key, handler), token])

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


class Ros2Base:
    """The leader's base as a ROS 2 robot, a FollowerLink of one: each tick's leader (v, w) goes
    out on its command topic (Twist, or TwistStamped), its odometry (nav_msgs/msg/Odometry on
    ``odom_topic``) is what it measured. No odometry for ODOM_TIMEOUT_S: it is ``lost``, measured
    (0, 0) (the leader counts as stopped), and its state says so."""

    n = 1

    def __init__(self, node: Ros2Node, cmd_topic: str = "/cmd_vel", stamped: bool = False,
                 odom_topic: str = "/odom", clock: Callable[[], float] = time.monotonic) -> None:
        self.node = node
        self.cmd_topic, self.stamped = cmd_topic, stamped
        self._cmd = node.publisher(cmd_topic, TWIST_STAMPED if stamped else TWIST)
        self._clock = clock
        self._lock = threading.Lock()
        self._odom: tuple[float, float, float] | None = None  # (v, w, monotonic time it came)
        self.odom_pose: tuple[float, float, float] | None = None
        self.odometry = 0
        node.subscribe(odom_topic, ODOMETRY, self._on_odom)

    def _on_odom(self, m: Any) -> None:
        v, w = finite_twist(m.twist.twist)
        p = m.pose.pose
        with self._lock:
            self._odom = (v, w, self._clock())
            self.odom_pose = (float(p.position.x), float(p.position.y), yaw_of(p.orientation))
            self.odometry += 1

    @property
    def lost(self) -> bool:
        with self._lock:
            return self._odom is None or self._clock() - self._odom[2] > ODOM_TIMEOUT_S

    @property
    def link_state(self) -> str:
        if self._odom is None:
            return f"ros2 {self.cmd_topic}: no odometry yet"
        return f"ros2 {self.cmd_topic}: no odometry for {ODOM_TIMEOUT_S:g} s" if self.lost else f"ros2 {self.cmd_topic}"

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
        return f"leader base: {self.odometry} odometry messages, {self.node.dropped} malformed dropped"

    def close(self) -> None:
        try:
            self.send(Commands.zeros(1))  # the base stops when we go
        except Exception:  # noqa: BLE001 - the session may be gone
            pass
