"""The follower protocol (core/link/protocol.py) and the follower firmware rules (core/link/follower.py)."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.link import protocol as p
from core.link.follower import FollowerHardware, FollowerState, handle_frame, step_follower

HW = FollowerHardware()


def test_crc_is_ccitt_false():
    assert p.crc16(b"123456789") == 0x29B1  # the catalogue check value of CRC-16/CCITT-FALSE


def test_example_frame_of_the_protocol_document():
    # docs/follower-protocol.md shows this frame: follower 1, seq 7, v = 0.1 m/s, w = -0.25 rad/s
    raw = p.encode_frame(p.set_velocity(1, 7, 0.1, -0.25))
    assert raw.hex(" ") == "a5 5a 01 07 01 04 64 00 06 ff 7a 84"
    assert p.FrameParser().feed(raw) == [p.set_velocity(1, 7, 0.1, -0.25)]


def test_ownership_example_frames_of_the_protocol_document():
    # docs/follower-protocol.md, "Ownership (protocol 2)": each example frame, and back
    examples = [
        (p.claim(3, 20, 1, 1000), "a5 5a 03 14 04 03 01 e8 03 fb b9"),
        (p.drive(3, 21, 1, 40, 0.1, -0.25), "a5 5a 03 15 06 07 01 28 00 64 00 06 ff dd c0"),
        (p.handover(3, 22, 1, 2, 1000), "a5 5a 03 16 05 04 01 02 e8 03 be 14"),
        (p.owner(3, 20, p.Ownership(1, 1000, 0, 1)), "a5 5a 03 14 83 04 01 e8 03 01 66 a6"),
        (p.nack(3, 23, p.Ownership(1, 640, p.NACK_OWNED, 2)), "a5 5a 03 17 84 05 01 80 02 01 02 de ec"),
    ]
    for frame, wire in examples:
        assert p.encode_frame(frame).hex(" ") == wire
        assert p.FrameParser().feed(bytes.fromhex(wire)) == [frame]
    assert p.decode_claim(examples[0][0]) == (1, 1000)
    assert p.decode_drive(examples[1][0]) == p.Drive(1, 40, 0.1, -0.25)
    assert p.decode_handover(examples[2][0]) == (1, 2, 1000)
    assert p.decode_ownership(examples[4][0]) == p.Ownership(1, 640, p.NACK_OWNED, 2)
    assert p.answers(examples[4][0]) == 2 and p.answers(examples[3][0]) == 1 and p.answers(examples[0][0]) is None
    a = p.Ack(1520, 1544, 0.098, -0.247, 0)
    (back,) = p.FrameParser().feed(p.encode_frame(p.driven(3, 21, a, 1)))
    assert p.decode_driven(back) == (a, 1) and p.answers(back) == 1


@given(st.floats(-40, 40), st.floats(-40, 40), st.integers(0, 255), st.integers(0, 255))
def test_set_velocity_round_trip_within_a_millimetre(v, w, addr, seq):
    frame = p.set_velocity(addr, seq, v, w)
    (back,) = p.FrameParser().feed(p.encode_frame(frame))
    bv, bw = p.decode_velocity(back)
    assert (back.address, back.seq) == (addr, seq)
    assert abs(bv - np.clip(v, -32.767, 32.767)) <= 0.0005 + 1e-12
    assert abs(bw - np.clip(w, -32.767, 32.767)) <= 0.0005 + 1e-12


def test_nan_commands_encode_as_zero():
    assert p.decode_velocity(p.set_velocity(1, 0, math.nan, math.nan)) == (0.0, 0.0)


@given(st.integers(-2**31, 2**31 - 1), st.integers(-2**31, 2**31 - 1), st.integers(-32767, 32767),
       st.integers(-32767, 32767), st.integers(0, 255))
def test_ack_round_trip(left, right, v, w, flags):
    a = p.Ack(left, right, v / 1000, w / 1000, flags)
    (back,) = p.FrameParser().feed(p.encode_frame(p.ack(3, 9, a)))
    assert p.decode_ack(back) == a


@given(st.integers(0, 0xFFFF), st.integers(0, 255), st.integers(0, 0xFFFF), st.integers(0, 2**32 - 1))
def test_status_round_trip(mv, flags, age, up):
    s = p.Status(mv, flags, age, up)
    (back,) = p.FrameParser().feed(p.encode_frame(p.status(4, 1, s)))
    assert p.decode_status(back) == s


@given(st.lists(st.tuples(st.integers(0, 255), st.floats(-1, 1), st.floats(-3, 3)), max_size=20),
       st.lists(st.integers(1, 40), min_size=1, max_size=50))
def test_any_chunking_gives_the_same_frames(cmds, cuts):
    frames = [p.set_velocity(a, k % 256, v, w) for k, (a, v, w) in enumerate(cmds)]
    stream = b"".join(p.encode_frame(f) for f in frames)
    parser, got, pos, k = p.FrameParser(), [], 0, 0
    while pos < len(stream):
        step = cuts[k % len(cuts)]
        got += parser.feed(stream[pos:pos + step])
        pos, k = pos + step, k + 1
    assert got == frames and parser.rejected_total == 0 and parser.skipped_bytes == 0


@settings(max_examples=300)
@given(st.binary(max_size=600))
def test_parser_never_raises_on_random_bytes(data):
    parser = p.FrameParser()
    for frame in parser.feed(data) + parser.feed(data[::-1]):
        assert frame.msg_type in p.PAYLOAD_LEN  # anything it accepts is a well-formed frame
    assert len(parser.buffer) < p.MAX_FRAME


def test_a_million_random_and_corrupted_bytes():
    """10^6 bytes of noise, then valid frames with every third one corrupted, in random chunks:
    the parser never raises, returns exactly the intact frames and counts every corrupted one."""
    rng = np.random.default_rng(7)
    noise = rng.bytes(1_000_000)
    parser = p.FrameParser()
    pos = 0
    while pos < len(noise):
        step = int(rng.integers(1, 4096))
        parser.feed(noise[pos:pos + step])
        pos += step
    noise_rejects = parser.rejected_total
    assert parser.frames_ok + noise_rejects <= noise.count(p.SYNC)

    stream, intact, corrupted = bytearray(), [], 0
    for k in range(3000):
        frame = p.set_velocity(int(rng.integers(1, 9)), k % 256, float(rng.uniform(-0.3, 0.3)), float(rng.uniform(-2, 2)))
        raw = bytearray(p.encode_frame(frame))
        if k % 3 == 0:
            j = int(rng.integers(2, len(raw)))  # anywhere after the sync bytes
            raw[j] ^= 1 << int(rng.integers(0, 8))
            corrupted += 1
        else:
            intact.append(frame)
        stream += raw
        gap = bytes(b for b in rng.bytes(int(rng.integers(0, 6))) if b != 0xA5)  # noise that cannot start a frame
        stream += gap
    parser2 = p.FrameParser()
    got, pos = [], 0
    while pos < len(stream):
        step = int(rng.integers(1, 64))
        got += parser2.feed(bytes(stream[pos:pos + step]))
        pos += step
    assert got == intact
    assert parser2.rejected_total >= corrupted
    assert parser2.frames_ok + parser2.rejected_total <= bytes(stream).count(p.SYNC)
    assert sum(parser.rejected.values()) == noise_rejects


def test_unknown_types_and_wrong_lengths_are_refused_and_counted():
    parser = p.FrameParser()
    unknown = p.encode_frame(p.Frame(1, 0, 0x55, b"xy"))
    short_velocity = p.encode_frame(p.Frame(1, 0, p.MSG_SET_VELOCITY, b"\x01"))
    too_long = bytearray(p.encode_frame(p.ping(1, 0)))
    too_long[5] = p.MAX_PAYLOAD + 1
    bad_crc = bytearray(p.encode_frame(p.ping(3, 0)))
    bad_crc[-1] ^= 0x10
    good = p.encode_frame(p.ping(2, 5))
    assert parser.feed(unknown + short_velocity + bytes(too_long) + bytes(bad_crc) + good) == [p.ping(2, 5)]
    assert parser.rejected == {"crc": 1, "length": 2, "type": 1}
    assert parser.last_rejects == [("type", 1), ("length", 1), ("length", 1), ("crc", 3)]


# -- the follower's firmware rules ------------------------------------------------------------


def run(s: FollowerState, seconds: float, dt: float = 0.005) -> FollowerState:
    for _ in range(int(round(seconds / dt))):
        s = step_follower(s, HW, dt)
    return s


def test_set_velocity_drives_the_wheels_and_the_encoders_count():
    s, reply = handle_frame(FollowerState(1), HW, p.set_velocity(1, 3, 0.2, 0.5))
    assert reply is not None and reply.msg_type == p.MSG_ACK and reply.seq == 3
    for _ in range(8):  # keep feeding the watchdog for 0.8 s
        s = run(s, 0.1)
        s, _ = handle_frame(s, HW, p.set_velocity(1, 4, 0.2, 0.5))
    v, w = s.measured(HW)
    assert v == pytest.approx(0.2, abs=1e-3) and w == pytest.approx(0.5, abs=1e-2)
    left, right = s.ticks(HW)
    assert right > left > 0  # turning left: the right wheel travels further
    ack = p.decode_ack(handle_frame(s, HW, p.set_velocity(1, 5, 0.2, 0.5))[1])
    assert (ack.left_ticks, ack.right_ticks) == (left, right) and ack.flags == 0


def test_the_watchdog_stops_a_follower_whose_last_command_is_older_than_half_a_second():
    s, _ = handle_frame(FollowerState(1), HW, p.set_velocity(1, 0, 0.2, 0.0))
    s = run(s, 0.45)
    assert s.target_l_mps == pytest.approx(0.2) and not s.flags & p.FLAG_WATCHDOG
    s, _ = handle_frame(s, HW, p.ping(1, 1))  # a ping is not a command: it does not feed the watchdog
    s = run(s, 0.10)
    assert s.target_l_mps == 0.0 and s.target_r_mps == 0.0 and s.flags & p.FLAG_WATCHDOG
    s = run(s, 1.0)
    assert not s.moving
    s, reply = handle_frame(s, HW, p.set_velocity(1, 2, 0.1, 0.0))  # a new command clears it
    assert not s.flags & p.FLAG_WATCHDOG and p.decode_ack(reply).flags == 0


def test_stop_broadcast_and_addressing():
    s, _ = handle_frame(FollowerState(2), HW, p.set_velocity(2, 0, 0.2, 0.0))
    other, reply = handle_frame(s, HW, p.set_velocity(3, 0, 0.3, 0.0))
    assert other == s and reply is None  # not for us
    stopped, reply = handle_frame(s, HW, p.stop(p.BROADCAST, 1))
    assert reply is None and stopped.target_l_mps == 0.0 and stopped.flags & p.FLAG_STOPPED
    st_frame = handle_frame(stopped, HW, p.ping(2, 9))[1]
    status = p.decode_status(st_frame)
    assert status.flags & p.FLAG_STOPPED and status.battery_mv == HW.battery_mv and st_frame.seq == 9


def test_every_example_frame_in_the_protocol_document_is_valid():
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[3] / "docs" / "follower-protocol.md").read_text()
    examples = re.findall(r"`(a5 5a(?: [0-9a-f]{2})+)`", doc)
    assert len(examples) == 12  # five of protocol 1, five of ownership (protocol 2), two authenticated (3)
    frames = []
    for hex_text in examples:
        raw = bytes.fromhex(hex_text)
        parser = p.FrameParser()
        (frame,) = parser.feed(raw)
        assert p.encode_frame(frame) == raw and parser.rejected_total == 0
        frames.append(frame)
    (ack,) = [p.decode_ack(f) for f in frames if f.msg_type == p.MSG_ACK]
    assert ack == p.Ack(1520, 1544, 0.098, -0.247, 0)
    (status,) = [p.decode_status(f) for f in frames if f.msg_type == p.MSG_STATUS]
    assert status == p.Status(7400, p.FLAG_WATCHDOG, 0xFFFF, 123456)
    assert "0x29B1" in doc and "0.5 s" in doc


def test_wheels_at_their_limit_are_scaled_together_so_the_path_keeps_its_curvature():
    from core.link.follower import FollowerHardware, wheel_targets

    hw = FollowerHardware()
    left, right = wheel_targets(0.4, 2.0, hw)  # 0.28 and 0.52 m/s asked, 0.45 the most
    assert max(abs(left), abs(right)) == pytest.approx(hw.wheel_speed_max_mps)
    assert (right - left) / hw.wheel_base_m / ((left + right) / 2) == pytest.approx(2.0 / 0.4)
    assert wheel_targets(0.1, 0.5, hw) == pytest.approx((0.1 - 0.03, 0.1 + 0.03))  # within limits: as asked
