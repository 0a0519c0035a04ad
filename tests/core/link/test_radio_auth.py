"""Authenticated frames (protocol 3, docs/follower-protocol.md "Authenticated frames"): SipHash-2-4
against its published vectors, the document's worked example byte for byte, and the follower's
refusals, each counted."""

from __future__ import annotations

import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from core.link import protocol as p
from core.link.follower import FollowerHardware, FollowerState, RadioAuth, handle_frame
from core.link.siphash import siphash24
from tests.core.link.siphash_vectors import KEY, VECTORS
from tests.helpers import ROOT

DOC = (ROOT / "docs" / "follower-protocol.md").read_text()
HW = FollowerHardware()
K = bytes(range(32))


def test_siphash_gives_the_published_test_vectors():
    assert [siphash24(KEY, bytes(range(n))) for n in range(64)] == VECTORS
    with pytest.raises(ValueError, match="16 bytes"):
        siphash24(bytes(15), b"")


def _doc_hex(after: str) -> bytes:
    """The first `hex bytes` in backquotes after ``after`` in the document."""
    tail = DOC[DOC.index(after) + len(after):]
    return bytes.fromhex(re.search(r"`((?:[0-9a-f]{2} )+[0-9a-f]{2})`", tail).group(1))


def test_the_documents_worked_example_byte_for_byte():
    drive = p.seal(p.drive(3, 21, 1, 40, 0.1, -0.25), K, 1, 1000)
    wire = p.encode_frame(drive)
    signed = bytes((3, 21, drive.msg_type, len(drive.payload))) + drive.payload[:-8]
    assert _doc_hex("- bytes signed (address .. counter):") == signed
    assert f"`0x{siphash24(K[:16], signed):016x}`" in DOC
    assert _doc_hex("on the wire\n") == p.tag_of(drive)
    assert _doc_hex("- the frame:") == wire and len(wire) == 30
    robot = FollowerState(3, owner=1, lease_ms=1000, lease_left_s=1.0)
    robot, reply = handle_frame(robot, HW, p.FrameParser().feed(wire)[0], RadioAuth((K,), (1,)))
    assert reply is not None and _doc_hex("followed by the request's tag `00 b2 a7 30 ca cd 72 77`:") == p.encode_frame(reply)
    opened = p.open_sealed(reply, (K,), p.tag_of(drive))
    assert opened is not None and (opened.ident, opened.counter) == (1, 1000)
    assert p.open_sealed(reply, (K,)) is None  # without the request's tag it does not verify


@given(st.binary(max_size=p.MAX_PAYLOAD - p.TRAILER_LEN), st.integers(0, p.COUNTER_MAX), st.integers(1, 250))
def test_sealed_frames_open_under_their_key_only(payload, counter, ident):
    frame = p.Frame(7, 9, p.MSG_PING, payload)
    sealed = p.seal(frame, K, ident, counter)
    opened = p.open_sealed(sealed, (bytes(32), K))
    assert opened is not None and opened == p.Sealed(frame, ident, counter, 1)
    assert p.open_sealed(sealed, (bytes(range(1, 33)),)) is None


def _robot(**kw) -> tuple[FollowerState, RadioAuth]:
    return FollowerState(5), RadioAuth((K,), (1, 2), **kw)


def test_a_robot_refuses_and_counts_every_kind_of_bad_frame_and_answers_none():
    s, auth = _robot()
    s, r = handle_frame(s, HW, p.seal(p.claim(5, 1, 1, 1000), K, 1, 10), auth)
    assert r is not None and r.msg_type == p.MSG_OWNER | p.AUTH and s.owner == 1
    bad = [
        p.drive(5, 2, 1, 0, 0.2, 0.0),                                    # plain
        p.seal(p.drive(5, 3, 1, 0, 0.2, 0.0), bytes(32), 1, 11),          # the open key is not the fleet's
        p.seal(p.drive(5, 4, 3, 0, 0.2, 0.0), K, 3, 12),                  # leader 3 is not the fleet's
        p.seal(p.drive(5, 5, 1, 0, 0.2, 0.0), K, 1, 10),                  # counter 10 again
    ]
    for frame in bad:
        s, r = handle_frame(s, HW, frame, auth)
        assert r is None and s.target_l_mps == 0.0
    assert s.refusals == p.RadioCounts(bad_mac=1, unknown_sender=1, replayed=1, unauthenticated=1)
    s, r = handle_frame(s, HW, p.seal(p.drive(5, 6, 1, 0, 0.2, 0.0), K, 1, 11), auth)
    assert r is not None and s.target_l_mps == pytest.approx(0.2)


@pytest.mark.parametrize("policy, stops", [("anyone", True), ("authenticated", False)])
def test_an_unauthenticated_stop_follows_the_provisioned_policy(policy, stops):
    s, auth = _robot(stop=policy)
    s, _ = handle_frame(s, HW, p.seal(p.set_velocity(5, 1, 0.2, 0.0), K, 1, 10), auth)
    assert s.target_l_mps > 0
    s, r = handle_frame(s, HW, p.stop(5, 2), auth)
    assert r is None and (s.target_l_mps == 0.0) is stops and bool(s.flags & p.FLAG_STOPPED) is stops
    assert s.refusals.unauthenticated == (0 if stops else 1)
