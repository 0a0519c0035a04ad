"""The channels Foxglove draws by itself — /tf, /camera/image, /scan — in Foxglove's own
schemas, taken from its published package (``foxglove-schemas-protobuf``) rather than
written by hand: protobuf encoding, and the schema embedded in the recording is the
package's FileDescriptorSet, as Foxglove's own SDK writes it. Our own channels (ticks,
events, params, trials) stay JSON with JSON-schema schemas.

The payloads are built as plain dicts (app.recording.schema) and turned into messages here,
on the recorder's writer thread.
"""

from __future__ import annotations

import math
from typing import Any

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from foxglove_schemas_protobuf.LaserScan_pb2 import LaserScan
from google.protobuf import descriptor_pb2
from google.protobuf.descriptor import FileDescriptor

from app.recording.schema import IMAGE_TOPIC, SCAN_TOPIC, TF_TOPIC

PROTOBUF_TOPICS: dict[str, Any] = {TF_TOPIC: FrameTransforms, IMAGE_TOPIC: CompressedImage, SCAN_TOPIC: LaserScan}


def schema_data(message_class: Any) -> bytes:
    """The message's FileDescriptorSet (its .proto file and every one it imports), serialised."""
    fds = descriptor_pb2.FileDescriptorSet()
    seen: set[str] = set()

    def add(fd: FileDescriptor) -> None:
        if fd.name in seen:
            return
        for dep in fd.dependencies:
            add(dep)
        seen.add(fd.name)
        fd.CopyToProto(fds.file.add())

    add(message_class.DESCRIPTOR.file)
    return bytes(fds.SerializeToString())


def _stamp(msg: Any, d: dict[str, int]) -> None:
    msg.timestamp.seconds = int(d["sec"])
    msg.timestamp.nanos = int(d["nsec"])


def _vec(msg: Any, d: dict[str, float]) -> None:
    msg.x, msg.y, msg.z = float(d["x"]), float(d["y"]), float(d["z"])


def encode(topic: str, payload: dict[str, Any]) -> bytes:
    """The message for ``topic`` from its dict payload (app.recording.schema)."""
    if topic == IMAGE_TOPIC:
        img = CompressedImage(frame_id=payload["frame_id"], data=payload["data"], format=payload["format"])
        _stamp(img, payload["timestamp"])
        return bytes(img.SerializeToString())
    if topic == TF_TOPIC:
        tf = FrameTransforms()
        for t in payload["transforms"]:
            m = tf.transforms.add()
            _stamp(m, t["timestamp"])
            m.parent_frame_id, m.child_frame_id = t["parent_frame_id"], t["child_frame_id"]
            _vec(m.translation, t["translation"])
            q = t["rotation"]
            m.rotation.x, m.rotation.y, m.rotation.z, m.rotation.w = q["x"], q["y"], q["z"], q["w"]
        return bytes(tf.SerializeToString())
    if topic == SCAN_TOPIC:
        scan = LaserScan(frame_id=payload["frame_id"], start_angle=payload["start_angle"],
                         end_angle=payload["end_angle"])
        _stamp(scan, payload["timestamp"])
        _vec(scan.pose.position, payload["pose"]["position"])
        q = payload["pose"]["orientation"]
        scan.pose.orientation.x, scan.pose.orientation.y = q["x"], q["y"]
        scan.pose.orientation.z, scan.pose.orientation.w = q["z"], q["w"]
        # free as far as the camera sees: no return, which LaserScan says with +inf
        scan.ranges.extend(math.inf if r is None or not math.isfinite(r) else float(r) for r in payload["ranges"])
        return bytes(scan.SerializeToString())
    raise KeyError(f"{topic}: not a Foxglove-schema channel")


def decode_image(data: bytes) -> bytes:
    """The JPEG of a recorded foxglove.CompressedImage (protobuf)."""
    return bytes(CompressedImage.FromString(data).data)


def decode(topic: str, data: bytes) -> Any:
    """A recorded protobuf message back (for tools and tests)."""
    return PROTOBUF_TOPICS[topic].FromString(data)
