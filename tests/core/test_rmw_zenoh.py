"""rmw_zenoh's wire format as its design document (docs/design.md) writes it, and REP-2011 type
hashes against hashes published elsewhere."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from core.rmw_zenoh import (
    MESSAGE_KINDS,
    NodeName,
    check_domain,
    check_topic,
    data_key,
    decode_attachment,
    encode_attachment,
    entity_gid,
)
from core.xxh3 import xxh3_128

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"

# Published RIHS01 hashes: std_msgs/msg/String from rmw_zenoh's docs/design.md (its examples);
# the others from keys of running rmw_zenoh systems (ROS 2 Jazzy).
PUBLISHED = {
    "std_msgs/msg/String": STRING_HASH,
    "geometry_msgs/msg/Twist": "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a",
    "sensor_msgs/msg/Imu": "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
    "sensor_msgs/msg/MagneticField": "RIHS01_e80f32f56a20486c9923008fc1a1db07bbb273cbbf6a5b3bfa00835ee00e4dff",
    "sensor_msgs/msg/FluidPressure": "RIHS01_22dfb2b145a0bd5a31a1ac3882a1b32148b51d9b2f3bab250290d66f3595bc32",
    "sensor_msgs/msg/Temperature": "RIHS01_72514a14126ab9f8a9abec974c78e5610a367b59db5da355ff1fb982d5bad4b8",
}


@pytest.mark.parametrize("ros_type", sorted(PUBLISHED))
def test_type_hashes_are_the_published_ones(ros_type):
    from app.backends.ros2 import type_hash

    assert type_hash(ros_type) == PUBLISHED[ros_type]


def test_an_unknown_type_is_one_line():
    from app.backends.ros2 import type_hash

    with pytest.raises(ValueError, match="unknown"):
        type_hash("geometry_msgs/msg/Nope")


def test_data_keys_are_the_design_documents_examples():
    assert data_key(0, "/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert data_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"


def test_liveliness_tokens_are_the_design_documents_examples():
    listener = NodeName(2, "aac3178e146ba6f1fc6e6a4085e77f21", "listener")
    assert listener.node_token() == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert listener.entity_token(10, "MS", "/chatter", "std_msgs/msg/String", STRING_HASH) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,10:,:,:,,")
    talker = NodeName(2, "8b20917502ee955ac4476e0266340d5c", "talker")
    assert talker.entity_token(10, "MP", "/chatter", "std_msgs/msg/String", STRING_HASH, qos="::,7:,:,:,,") == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,")
    assert set(MESSAGE_KINDS) == {"MP", "MS"}


def test_the_attachment_is_int64_int64_length_and_gid():
    gid = bytes(range(16))
    data = encode_attachment(7, 1_700_000_000_123_456_789, gid)
    assert data == struct.pack("<qqB", 7, 1_700_000_000_123_456_789, 16) + gid
    assert decode_attachment(data) == (7, 1_700_000_000_123_456_789, gid)
    for bad in (b"", data[:-1], data + b"\0", data[:16] + b"\x0f" + data[17:]):
        with pytest.raises(ValueError, match="attachment"):
            decode_attachment(bad)


@pytest.mark.parametrize("domain", [-1, 233, 10_000])
def test_a_domain_outside_rcls_range_is_refused(domain):
    with pytest.raises(ValueError, match=r"0\.\.232"):
        check_domain(domain)


@pytest.mark.parametrize("topic", ["cmd_vel", "/", "/cmd vel", "/1abc", "/a//b", "/a/", "/a__b", "/a/*", "/@ros2_lv"])
def test_a_name_that_is_not_a_ros_topic_is_refused(topic):
    with pytest.raises(ValueError, match="fully qualified"):
        check_topic(topic)


def test_xxh3_128_is_xxhashs():
    """The published XXH3-128 of nothing, and the xxHash library itself (where installed) for
    every length up to 600 bytes and a few long ones: every branch of the algorithm."""
    import ctypes
    import ctypes.util
    import os

    lo, hi = xxh3_128(b"")
    assert f"{hi:016x}{lo:016x}" == "99aa06d3014798d86001c324468d497f"
    path = ctypes.util.find_library("xxhash")
    if path is None:
        pytest.skip("no xxHash library here to compare with")
    lib = ctypes.CDLL(path)

    class Hash128(ctypes.Structure):
        _fields_ = [("low64", ctypes.c_uint64), ("high64", ctypes.c_uint64)]

    lib.XXH3_128bits.restype = Hash128
    lib.XXH3_128bits.argtypes = [ctypes.c_char_p, ctypes.c_size_t]
    rng = np.random.default_rng(3)
    for n in [*range(0, 600, 7), 1024, 4096]:
        data = rng.bytes(n) if n else os.urandom(0)
        h = lib.XXH3_128bits(data, n)
        assert xxh3_128(data) == (h.low64, h.high64), n


def test_a_gid_is_xxh3_128_of_the_token_low_half_first():
    token = "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/x"
    lo, hi = xxh3_128(token.encode())
    assert entity_gid(token) == struct.pack("<QQ", lo, hi)

