"""rmw_zenoh's wire format, pure: the key a topic's data travels on, the liveliness tokens that
make a node and its publishers and subscriptions visible to ROS 2 tools, and the attachment
every publication carries. Written from rmw_zenoh's own design document (docs/design.md,
"Topic and Service name mapping to Zenoh key expressions", "Graph Cache", "Publishers") and its
sources (rmw_zenoh_cpp/src/detail/liveliness_utils.cpp: ``TopicInfo``, ``Entity``,
``mangle_name``, ``qos_to_keyexpr``; attachment_helpers.cpp: ``AttachmentData``).

Type hashes (RIHS01, REP-2011) are not made here: app.backends.ros2 takes them from the ROS 2
type descriptions and checks them against published ones.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from core.xxh3 import xxh3_128

ADMIN_SPACE = "@ros2_lv"  # liveliness_utils.cpp: ADMIN_SPACE
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"  # the entity kinds this node declares
MESSAGE_KINDS = (PUBLISHER, SUBSCRIPTION)
# ROS_DOMAIN_ID: rcl accepts 0..232 (the highest a DDS port mapping allows; ROS 2's "Domain ID" doc).
DOMAIN_MAX = 232
# qos_to_keyexpr with rmw_zenoh's defaults (reliable, volatile, keep last) and depth 10, as in the design
# document's example tokens ("::,10:,:,:,,"): reliability:durability:history,depth:deadline:lifespan:liveliness.
QOS_DEPTH_10 = "::,10:,:,:,,"
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
_TOPIC = re.compile(r"/[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_TYPE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/msg/([A-Z][A-Za-z0-9]*)")
_HASH = re.compile(r"RIHS01_[0-9a-f]{64}")


def check_domain(domain: int) -> int:
    """A ROS_DOMAIN_ID rcl accepts (0..232), else ValueError (one line)."""
    if not 0 <= domain <= DOMAIN_MAX:
        raise ValueError(f"ROS 2 domain {domain}: must be 0..{DOMAIN_MAX} (ROS_DOMAIN_ID)")
    return domain


def check_topic(topic: str) -> str:
    """A fully qualified ROS 2 topic name (``/a/b``: tokens of letters, digits and _, not starting
    with a digit), else ValueError (one line)."""
    if not _TOPIC.fullmatch(topic) or "__" in topic:
        raise ValueError(f"ROS 2 topic {topic!r}: must be a fully qualified name like /cmd_vel"
                         " (tokens of A-Z, a-z, 0-9 and _, none starting with a digit)")
    return topic


def dds_type(ros_type: str) -> str:
    """``geometry_msgs/msg/Twist`` -> ``geometry_msgs::msg::dds_::Twist_`` (the type name "as
    declared in DDS when encoded in CDR", design.md)."""
    m = _TYPE.fullmatch(ros_type)
    if m is None:
        raise ValueError(f"ROS 2 type {ros_type!r}: must be package/msg/Name")
    return f"{m[1]}::msg::dds_::{m[2]}_"


def mangle(name: str) -> str:
    """liveliness_utils.cpp ``mangle_name``: every ``/`` becomes ``%``."""
    return name.replace("/", "%")


def data_key(domain: int, topic: str, ros_type: str, type_hash: str) -> str:
    """``<domain_id>/<fully_qualified_name>/<type_name>/<type_hash>``, the topic's leading and
    trailing ``/`` stripped (``TopicInfo``'s ``strip_slashes``)."""
    if not _HASH.fullmatch(type_hash):
        raise ValueError(f"type hash {type_hash!r}: must be RIHS01_ and 64 hex digits")
    return f"{check_domain(domain)}/{check_topic(topic).strip('/')}/{dds_type(ros_type)}/{type_hash}"


@dataclass(frozen=True)
class NodeName:
    """Who a node is on the graph: domain, the Zenoh session's id, the node's id within the
    session, namespace ("/" for none), name and SROS enclave ("" for none)."""

    domain: int
    zid: str
    name: str
    namespace: str = "/"
    enclave: str = ""
    node_id: int = 0

    def _head(self, entity_id: int, kind: str) -> str:
        # An empty part would make "//" (not a key): rmw_zenoh writes it as "%" (mangle of "/" or of "").
        enclave = mangle(self.enclave) or "%"
        namespace = mangle(self.namespace) or "%"
        return (f"{ADMIN_SPACE}/{check_domain(self.domain)}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
                f"{enclave}/{namespace}/{mangle(self.name)}")

    def node_token(self) -> str:
        """``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>``."""
        if not _NAME.fullmatch(self.name):
            raise ValueError(f"ROS 2 node name {self.name!r}: letters, digits and _")
        return self._head(self.node_id, NODE)

    def entity_token(self, entity_id: int, kind: str, topic: str, ros_type: str, type_hash: str,
                     qos: str = QOS_DEPTH_10) -> str:
        """A publisher's (``MP``) or subscription's (``MS``) token: the node's, then the mangled
        topic, the DDS type, the type hash and the QoS."""
        if kind not in MESSAGE_KINDS:
            raise ValueError(f"entity kind {kind!r}: MP or MS")
        data_key(self.domain, topic, ros_type, type_hash)  # the same checks as its data key
        return f"{self._head(entity_id, kind)}/{mangle(topic)}/{dds_type(ros_type)}/{type_hash}/{qos}"


def entity_gid(token: str) -> bytes:
    """An entity's 16-byte GID as rmw_zenoh makes it (``Entity::Entity``): XXH3-128 of its
    liveliness token, the low 64 bits then the high 64 bits, little-endian."""
    lo, hi = xxh3_128(token.encode())
    return lo.to_bytes(8, "little") + hi.to_bytes(8, "little")


def encode_attachment(sequence: int, source_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment (design.md, "Publishers"; ``AttachmentData::serialize_to_zbytes``,
    zenoh's serializer): int64 sequence number and int64 source timestamp (ns since the UNIX
    epoch), both little-endian, then the GID as a sequence: its length (one LEB128 byte, 16)
    and its 16 bytes."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID is {GID_SIZE} bytes, not {len(gid)}")
    return struct.pack("<qqB", sequence, source_ns, GID_SIZE) + gid


def decode_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) from an attachment, else ValueError."""
    if len(data) != ATTACHMENT_SIZE or data[16] != GID_SIZE:
        raise ValueError(f"attachment of {len(data)} bytes: rmw_zenoh's is {ATTACHMENT_SIZE}"
                         f" (int64, int64, length {GID_SIZE}, GID)")
    sequence, stamp, _ = struct.unpack_from("<qqB", data)
    return int(sequence), int(stamp), bytes(data[17:])


@dataclass(frozen=True)
class EntityToken:
    """A publisher's or subscription's liveliness token as read off the graph: its kind (``MP``,
    ``MS``), the node (``namespace/name``), the topic (``/a/b``), the DDS type and the GID
    rmw_zenoh gives it (XXH3-128 of the whole token)."""

    key: str
    kind: str
    node: str
    topic: str
    dds_type: str

    @property
    def gid(self) -> bytes:
        return entity_gid(self.key)


def parse_entity_token(key: str, domain: int) -> EntityToken | None:
    """A ``MP``/``MS`` token of ``domain`` (``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/
    <namespace>/<node>/<topic>/<type>/<hash>/<qos>``), else None (a node's token, another domain,
    something that is not a token)."""
    parts = key.split("/")
    if len(parts) < 13 or parts[0] != ADMIN_SPACE or parts[1] != str(domain) or parts[5] not in MESSAGE_KINDS:
        return None
    namespace = parts[7].replace("%", "/").rstrip("/")
    return EntityToken(key, parts[5], f"{namespace}/{parts[8]}", parts[9].replace("%", "/"), parts[10])
