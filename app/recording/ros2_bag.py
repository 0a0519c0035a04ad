"""A recording as a ROS 2 bag (rosbag2: MCAP storage, CDR, metadata.yaml), built with
``rosbags`` and its ROS 2 Jazzy types, so ROS tools (ros2 bag, rviz2, PlotJuggler, Foxglove)
read our sessions without a ROS install here. docs/foxglove.md lists the topics.

Every message is stamped (header and bag time) with the session's time: the recording's
``start_ns`` plus the tick's (or frame's) session time. Frames: ``world`` (the simulator's /
odometry's), ``leader`` (x right, y forward, as everywhere here), ``follower<i>`` (estimate, in
the leader frame), ``follower<i>_true`` (simulation truth, in the world; absent for real robots).
Velocities follow ROS's body convention (REP 103: x forward, z up): ``linear.x`` is a robot's
forward speed (m/s), ``angular.z`` its turn rate (rad/s).

Per tick (one message per readable tick on each): /tf, /omniformation/followers and
/omniformation/slots (PoseArray in the leader frame, one pose per follower in follower order; NaN
while a follower has not been seen), /omniformation/follower<i>/error (Vector3Stamped: its slot
minus its estimate, leader frame, m), /cmd_vel (the leader's command) and
/omniformation/follower<i>/cmd_vel (each follower's). Per recorded camera frame:
/camera/image/compressed. A damaged recording exports what the reader could read; what was
lost is reported (app.recording.reader's loss note) and kept in the bag's custom data.
"""

from __future__ import annotations

import math
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from app.recording.reader import Recording
from app.recording.schema import tick_from_payload, transforms_payload

TF_TYPE = "tf2_msgs/msg/TFMessage"
POSES_TYPE = "geometry_msgs/msg/PoseArray"
IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
TWIST_TYPE = "geometry_msgs/msg/Twist"
ERROR_TYPE = "geometry_msgs/msg/Vector3Stamped"
BAD_TICK = (KeyError, TypeError, ValueError, IndexError, AttributeError, OSError)


class BagRefused(ValueError):
    """The bag cannot be written where asked (exists, not a bag, no folder): one line."""


@dataclass
class ExportResult:
    path: Path
    ticks: int = 0  # ticks exported
    frames: int = 0  # camera frames exported
    unreadable: int = 0  # ticks or frames the reader listed but could not give back
    loss: str = ""  # what the recording had lost before (the reader's note)
    counts: dict[str, int] = field(default_factory=dict)  # messages per topic


def _is_bag(path: Path) -> bool:
    """A folder rosbag2 wrote: metadata.yaml, and nothing but bag files beside it."""
    if not (path / "metadata.yaml").is_file():
        return False
    return all(p.is_file() and p.suffix in (".yaml", ".mcap", ".db3", ".zstd") for p in path.iterdir())


def check_target(path: Path, overwrite: bool) -> None:
    """BagRefused (one line) unless a bag may be written at ``path``."""
    if not path.parent.is_dir():
        raise BagRefused(f"--ros2 {path}: folder {path.parent} does not exist")
    if path.exists() or path.is_symlink():
        if not overwrite:
            raise BagRefused(f"--ros2 {path}: exists; give --overwrite to replace it, or another folder")
        if not path.is_dir() or path.is_symlink() or not _is_bag(path):
            raise BagRefused(f"--ros2 {path}: exists and is not a ROS 2 bag; it is never replaced (give another"
                             " folder)")


class _Bag:
    """The writer, its typestore and one connection per topic (made on first use)."""

    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.ts = get_typestore(Stores.ROS2_JAZZY)
        self.T = self.ts.types
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def stamp(self, ns: int, frame: str) -> Any:
        return self.T["std_msgs/msg/Header"](
            stamp=self.T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000),
            frame_id=frame)

    def vec(self, x: float, y: float, z: float) -> Any:
        return self.T["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))

    def quat(self, yaw: float) -> Any:
        return self.T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))

    def pose(self, x: float, y: float, yaw: float) -> Any:
        return self.T["geometry_msgs/msg/Pose"](position=self.T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                                orientation=self.quat(yaw))

    def twist(self, v: float, w: float) -> Any:
        return self.T[TWIST_TYPE](linear=self.vec(v, 0.0, 0.0), angular=self.vec(0.0, 0.0, w))

    def write(self, topic: str, msgtype: str, msg: Any, ns: int) -> None:
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
            self.counts[topic] = 0
        self.writer.write(conn, ns, self.ts.serialize_cdr(msg, msgtype))
        self.counts[topic] += 1


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _tick(bag: _Bag, d: dict[str, Any], ns: int) -> None:
    """One recorded tick's messages (see the module docstring)."""
    T = bag.T
    s = tick_from_payload(d)
    transforms = []
    for t in transforms_payload(s, ns)["transforms"]:  # the recording's own /tf, as ROS's TFMessage
        tr, q = t["translation"], t["rotation"]
        if not _finite(tr["x"], tr["y"], q["z"], q["w"]):
            continue  # tf2 refuses NaN: a pose not known this tick is left out
        transforms.append(T["geometry_msgs/msg/TransformStamped"](
            header=bag.stamp(ns, t["parent_frame_id"]), child_frame_id=t["child_frame_id"],
            transform=T["geometry_msgs/msg/Transform"](
                translation=bag.vec(tr["x"], tr["y"], tr["z"]),
                rotation=T["geometry_msgs/msg/Quaternion"](x=q["x"], y=q["y"], z=q["z"], w=q["w"]))))
    bag.write("/tf", TF_TYPE, T[TF_TYPE](transforms=transforms), ns)
    bag.write("/omniformation/followers", POSES_TYPE, T[POSES_TYPE](
        header=bag.stamp(ns, "leader"),
        poses=[bag.pose(s.p_est[i, 0], s.p_est[i, 1], s.a_est[i]) for i in range(s.n)]), ns)
    bag.write("/omniformation/slots", POSES_TYPE, T[POSES_TYPE](
        header=bag.stamp(ns, "leader"), poses=[bag.pose(s.p_d[i, 0], s.p_d[i, 1], math.pi / 2) for i in range(s.n)]), ns)
    bag.write("/cmd_vel", TWIST_TYPE, bag.twist(*s.leader_twist), ns)
    err = s.p_d - s.p_est
    for i in range(s.n):
        bag.write(f"/omniformation/follower{i + 1}/error", ERROR_TYPE,
                  T[ERROR_TYPE](header=bag.stamp(ns, "leader"), vector=bag.vec(err[i, 0], err[i, 1], 0.0)), ns)
        bag.write(f"/omniformation/follower{i + 1}/cmd_vel", TWIST_TYPE, bag.twist(*s.commands[i]), ns)


def export_ros2(rec: Recording, out: Path, overwrite: bool = False,
                progress: Callable[[int, int], None] | None = None) -> ExportResult:
    """Write ``rec`` as a rosbag2 folder at ``out`` (see the module docstring). The bag is built
    beside ``out`` and moved into place when whole: a failed export never leaves half a bag, and
    ``--overwrite`` replaces only a folder that is a ROS 2 bag."""
    check_target(out, overwrite)
    try:
        start_ns = int(rec.metadata.get("start_ns", "0") or 0)
    except ValueError:
        start_ns = 0
    work = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    result = ExportResult(out, loss=rec.loss_note())
    try:
        writer = Writer(work / out.name, version=9, storage_plugin=StoragePlugin.MCAP)
        writer.set_custom_data("omniformation.recording", rec.path.name)
        if result.loss:
            writer.set_custom_data("omniformation.loss", result.loss)
        writer.open()
        bag = _Bag(writer)
        total = len(rec.ticks)
        frames = len(rec.frames)
        k_frame = 0
        for k in range(total):
            t = float(rec.t[k])
            while k_frame < frames and float(rec.frame_t[k_frame]) <= t:  # frames in time order among the ticks
                result.frames += _frame(bag, rec, k_frame, start_ns)
                k_frame += 1
            try:
                _tick(bag, rec.ticks[k], start_ns + max(0, int(round(t * 1e9))))
                result.ticks += 1
            except BAD_TICK:
                result.unreadable += 1
            if progress is not None and (k + 1) % 600 == 0:
                progress(k + 1, total)
        while k_frame < frames:
            result.frames += _frame(bag, rec, k_frame, start_ns)
            k_frame += 1
        result.unreadable += frames - result.frames
        writer.close()
        if out.exists():
            shutil.rmtree(out)  # a bag (check_target), and --overwrite was given
        (work / out.name).rename(out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result.counts = dict(bag.counts)
    return result


def _frame(bag: _Bag, rec: Recording, k: int, start_ns: int) -> int:
    """One recorded camera frame as sensor_msgs/CompressedImage; 1, or 0 when unreadable."""
    try:
        t, jpeg = rec.frames[k]
    except BAD_TICK:
        return 0
    ns = start_ns + max(0, int(round(float(t) * 1e9)))
    bag.write("/camera/image/compressed", IMAGE_TYPE, bag.T[IMAGE_TYPE](
        header=bag.stamp(ns, "leader"), format="jpeg", data=np.frombuffer(jpeg, dtype=np.uint8)), ns)
    return 1
