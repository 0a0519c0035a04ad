"""The loop's state on ROS 2 topics, and (``--ros2-control``) STOP and goals from ROS.

Like the fleet bridge it only reads what the loop publishes (``on_tick``, handed the newest
TickState; the newest wins, on its own thread, so the loop never waits for the network) and
changes the loop only through the ParamsStore, with the page's checks (docs/ros2.md lists the
topics, frames and types).
"""

from __future__ import annotations

import json
import math
import time
from typing import Any

import numpy as np

from app.backends.ros2 import Ros2Node, header, msg, pose, quaternion_yaw, vector3
from app.params import ParamsStore
from core.bounds import ROS
from app.tick import LatestStatePublisher, TickState

WORLD, LEADER = "world", "leader"  # TF frames: the odometry (world) frame and the leader frame
TOPICS = {  # topic -> ROS 2 type, what the node publishes
    "/tf": "tf2_msgs/msg/TFMessage",
    "/omniformation/followers": "geometry_msgs/msg/PoseArray",
    "/omniformation/slots": "geometry_msgs/msg/PoseArray",
    "/omniformation/formation_error": "std_msgs/msg/Float64MultiArray",
    "/omniformation/camera/compressed": "sensor_msgs/msg/CompressedImage",
    "/omniformation/status": "std_msgs/msg/String",
}
STOP_TOPIC, GOAL_TOPIC = "/omniformation/stop", "/omniformation/goal"
GOAL_FRAMES = ("", WORLD, "odom")  # a goal is in the odometry frame the leader started in
GOAL_UNIT_TOLERANCE = 0.01  # a goal's orientation is a unit quaternion within this


def goal_refusal(m: Any) -> str:
    """Why a PoseStamped goal is refused ("" when it is not): a frame other than the odometry
    frame's names, a position or orientation that is not finite, an orientation that is not a unit
    quaternion (|q| within GOAL_UNIT_TOLERANCE of 1; all zeros, a forgotten orientation, is not)."""
    x, y, z = (float(v) for v in (m.pose.position.x, m.pose.position.y, m.pose.position.z))
    q = m.pose.orientation
    quat = [float(v) for v in (q.x, q.y, q.z, q.w)]
    if m.header.frame_id not in GOAL_FRAMES:
        return f"frame {m.header.frame_id!r} (must be world, odom or empty)"
    if not all(math.isfinite(v) for v in (x, y, z, *quat)):
        return "position or orientation not finite"
    norm = math.sqrt(sum(v * v for v in quat))
    if abs(norm - 1.0) > GOAL_UNIT_TOLERANCE:
        return f"orientation not a unit quaternion (|q| = {norm:.3g})"
    return ""


def transform(parent: str, child: str, x: float, y: float, yaw: float, ns: int) -> Any:
    return msg("geometry_msgs/msg/TransformStamped", header=header(parent, ns), child_frame_id=child,
               transform=msg("geometry_msgs/msg/Transform", translation=vector3(x, y), rotation=quaternion_yaw(yaw)))


def tf_message(s: TickState, ns: int) -> Any:
    """world -> leader (the leader frame has y forward: its yaw is the heading minus 90°), and
    leader -> follower_i where the controller took each follower to be (p_est, a_est)."""
    x, y, theta = (float(v) for v in s.leader)
    tfs = [transform(WORLD, LEADER, x, y, theta - math.pi / 2, ns)]
    for i in range(s.n):
        px, py, a = float(s.p_est[i, 0]), float(s.p_est[i, 1]), float(s.a_est[i])
        if math.isfinite(px) and math.isfinite(py):
            tfs.append(transform(LEADER, f"follower_{i + 1}", px, py, a if math.isfinite(a) else 0.0, ns))
    return msg("tf2_msgs/msg/TFMessage", transforms=tfs)


def pose_array(points: np.ndarray, yaws: np.ndarray | None, ns: int) -> Any:
    poses = [pose(float(p[0]), float(p[1]), float(yaws[i]) if yaws is not None and math.isfinite(yaws[i])
                  else math.pi / 2) for i, p in enumerate(points) if np.all(np.isfinite(p))]
    return msg("geometry_msgs/msg/PoseArray", header=header(LEADER, ns), poses=poses)


def status_text(s: TickState, base: str) -> str:
    """The status message: JSON with the loop's state for people and tools."""
    return json.dumps({"tick": s.tick, "t": round(s.t, 3), "stopped": bool(s.stopped), "paused": bool(s.paused),
                       "leader_waits": s.leader_waits, "link": s.link_state, "rate_hz": round(s.rate_hz, 2),
                       "phase": s.phase, "fault": s.fault, "leader_base": base})


class Ros2Bridge:
    """Publishes every tick it gets to (the newest wins) and, with ``allow_control``, takes STOP
    (std_msgs/msg/Bool: true stops, false releases) and goals (geometry_msgs/msg/PoseStamped in
    the world frame) into the store as the page does. ``base_state``: the leader base's state
    for the status message."""

    def __init__(self, node: Ros2Node, store: ParamsStore, allow_control: bool = False, frames_hz: float = 10.0,
                 base_state: Any = None) -> None:
        self.node, self.store = node, store
        self.pubs = {topic: node.publisher(topic, ros_type) for topic, ros_type in TOPICS.items()}
        self.frames_dt = 1.0 / frames_hz if frames_hz > 0 else math.inf
        self._last_frame = -math.inf
        self.base_state = base_state
        self.taken = self.refused = 0
        self.events: list[tuple[str, str]] = []
        if allow_control:
            node.subscribe(STOP_TOPIC, "std_msgs/msg/Bool", self._on_stop)
            node.subscribe(GOAL_TOPIC, "geometry_msgs/msg/PoseStamped", self._on_goal)
        # the newest state on a thread of its own, as the page's (a fault is logged, the thread goes on)
        self._publisher = LatestStatePublisher(self.publish, name="omniformation-ros2")

    @property
    def published(self) -> int:
        return self._publisher.published

    # -- out ----------------------------------------------------------------------------
    def on_tick(self, state: TickState) -> None:
        self._publisher(state)

    def publish(self, s: TickState) -> None:
        """Every topic a subscriber wants (a topic nobody subscribes to costs nothing)."""
        ns = time.time_ns()
        pubs = {topic: pub for topic, pub in self.pubs.items() if pub.wanted}
        if "/tf" in pubs:
            pubs["/tf"].put(tf_message(s, ns))
        if "/omniformation/followers" in pubs:
            pubs["/omniformation/followers"].put(pose_array(s.p_est, s.a_est, ns))
        if "/omniformation/slots" in pubs:
            pubs["/omniformation/slots"].put(pose_array(s.p_d, None, ns))
        if "/omniformation/formation_error" in pubs:
            err = np.linalg.norm(s.p_d - s.p_est, axis=1) if s.n else np.zeros(0)
            dim = msg("std_msgs/msg/MultiArrayDimension", label="follower", size=s.n, stride=s.n)
            pubs["/omniformation/formation_error"].put(msg(
                "std_msgs/msg/Float64MultiArray", layout=msg("std_msgs/msg/MultiArrayLayout", dim=[dim], data_offset=0),
                data=np.nan_to_num(err, nan=-1.0).astype(np.float64)))
        now = time.monotonic()
        if "/omniformation/camera/compressed" in pubs and s.frame is not None and now - self._last_frame >= self.frames_dt:
            import cv2

            ok, jpeg = cv2.imencode(".jpg", np.asarray(s.frame), [cv2.IMWRITE_JPEG_QUALITY, 80])
            if ok:
                self._last_frame = now
                pubs["/omniformation/camera/compressed"].put(msg(
                    "sensor_msgs/msg/CompressedImage", header=header("camera", ns), format="jpeg",
                    data=np.frombuffer(jpeg.tobytes(), dtype=np.uint8)))
        if "/omniformation/status" in pubs:
            base = "" if self.base_state is None else str(self.base_state())
            pubs["/omniformation/status"].put(msg("std_msgs/msg/String", data=status_text(s, base)))

    # -- in (--ros2-control) -----------------------------------------------------------
    def _apply(self, what: str, **changes: Any) -> bool:
        try:
            _, notices = self.store.update_from(ROS, f"ros2:{what}", **changes)  # the table's ROS rows only
        except (ValueError, TypeError) as exc:
            self.refused += 1
            self.events.append(("refused", f"ros2 {what}: {exc}"))
            return False
        if notices:
            self.events.extend(("refused", f"ros2 {what}: {n.message}") for n in notices)
        self.taken += 1
        return True

    def _on_stop(self, m: Any) -> None:
        self._apply(STOP_TOPIC, stop=bool(m.data))

    def _on_goal(self, m: Any) -> None:
        x, y = float(m.pose.position.x), float(m.pose.position.y)
        why = goal_refusal(m)
        if why:
            self.refused += 1
            self.events.append(("refused", f"ros2 goal: {why}"))
            from app.refusals import refuse  # per-message refusals: rate-limited, the first of each kind said

            refuse(f"ros2: goal refused: {why.split(' (')[0]}", GOAL_TOPIC, why)
            return
        if self._apply(GOAL_TOPIC, goal=(x, y)) and self.store.get().goal == (x, y):
            self._apply(GOAL_TOPIC, leader_mode="goal")  # as the page's "Drive to goal" (orientation unused)

    def close(self) -> None:
        self._publisher.close()
        for p in self.pubs.values():
            p.close()
