"""The follower link's wire format: framed, addressed, CRC-checked binary messages (pure).

The byte layout is specified for firmware authors in docs/follower-protocol.md; this
module is its reference implementation. Every multi-byte field is little-endian (the
MSP430 the paper's followers carry is little-endian), the CRC included.

    offset  size  field
    0       1     sync 0 = 0xA5
    1       1     sync 1 = 0x5A
    2       1     address: 1..250 a follower, 0 the leader base, 0xFF broadcast (no reply)
    3       1     sequence number (the host counts 0..255 and wraps; a reply echoes it)
    4       1     message type (MSG_*)
    5       1     payload length L, 0..MAX_PAYLOAD
    6       L     payload
    6+L     2     CRC-16/CCITT-FALSE over bytes 2 .. 5+L (address .. end of payload)

Protocol 3 wraps any of these in an authenticated frame (type | AUTH; :func:`seal`,
:func:`open_sealed`): the sender's id, a 48-bit counter and a SipHash-2-4 tag after the payload,
a reply's tag bound to the tag of the request it answers (docs/follower-protocol.md,
"Authenticated frames").

The parser (:class:`FrameParser`) never raises on any input: it resynchronises on the
sync bytes and counts what it rejects (bad CRC, impossible length, unknown type, a
payload whose length does not fit its type).
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass, field

from core.link.siphash import tag as _tag

SYNC = b"\xa5\x5a"
HEADER_LEN = 6  # sync (2), address, sequence, type, length
CRC_LEN = 2
MAX_PAYLOAD = 32
MAX_FRAME = HEADER_LEN + MAX_PAYLOAD + CRC_LEN

LEADER_ADDRESS = 0
BROADCAST = 0xFF
MAX_FOLLOWER_ADDRESS = 250

# host -> robot
MSG_SET_VELOCITY = 0x01  # int16 v (mm/s), int16 w (mrad/s); feeds the watchdog; answered by ACK
MSG_STOP = 0x02  # no payload: motors to zero at once, until the next SET_VELOCITY; answered by ACK
MSG_PING = 0x03  # no payload: answered by STATUS; does NOT feed the watchdog
# protocol 2: ownership (docs/follower-protocol.md, "Ownership")
MSG_CLAIM = 0x04  # uint8 leader, uint16 lease (ms): answered by OWNER (granted) or NACK
MSG_HANDOVER = 0x05  # uint8 from, uint8 to, uint16 lease (ms): the owner gives the robot away; OWNER or NACK
MSG_DRIVE = 0x06  # uint8 leader, uint16 observation age (ms), int16 v, int16 w: the owner's SET_VELOCITY; DRIVEN or NACK
# robot -> host
MSG_ACK = 0x81  # int32 left ticks, int32 right ticks, int16 v (mm/s), int16 w (mrad/s), uint8 flags
MSG_STATUS = 0x82  # uint16 battery (mV), uint8 flags, uint16 command age (ms), uint32 uptime (ms)
# protocol 2 replies name the leader they answer (on a shared radio every leader hears them all)
MSG_OWNER = 0x83  # uint8 owner, uint16 lease left (ms), uint8 asker: a CLAIM or HANDOVER granted
MSG_NACK = 0x84  # uint8 owner (0: none), uint16 lease left (ms), uint8 reason (NACK_*), uint8 asker: refused
MSG_DRIVEN = 0x85  # an ACK's 13 bytes, then uint8 asker: a DRIVE obeyed

PROTOCOL_VERSION = 2
NACK_OWNED = 1  # another leader owns the robot and its lease lives (CLAIM)
NACK_NOT_OWNER = 2  # the sender is not the owner, or the robot is owned and protocol 1 SET_VELOCITY came
NACK_STALE = 3  # DRIVE computed from an observation older than MAX_OBSERVATION_AGE_MS: the robot stops
MAX_OBSERVATION_AGE_MS = 300  # a DRIVE from an older observation moves nothing
LEASE_MIN_MS, LEASE_MAX_MS = 100, 10_000  # a lease asked for outside this is held to it
MAX_LEADER = 250  # leaders are numbered 1..250 on a radio (0: nobody)
FROM_A_LEADER = (MSG_CLAIM, MSG_HANDOVER, MSG_DRIVE)  # protocol 2 requests: each names its sender first

FLAG_WATCHDOG = 0x01  # stopped by the watchdog: no valid SET_VELOCITY for WATCHDOG_S
FLAG_STOPPED = 0x02  # stopped by a STOP message
FLAG_LOW_BATTERY = 0x04

WATCHDOG_S = 0.5  # a robot whose last valid SET_VELOCITY is older than this stops by itself

_ACK = struct.Struct("<iihhB")
_STATUS = struct.Struct("<HBHI")
_VELOCITY = struct.Struct("<hh")
_CLAIM = struct.Struct("<BH")
_HANDOVER = struct.Struct("<BBH")
_DRIVE = struct.Struct("<BHhh")
_OWNER = struct.Struct("<BHB")
_NACK = struct.Struct("<BHBB")
PAYLOAD_LEN = {MSG_SET_VELOCITY: _VELOCITY.size, MSG_STOP: 0, MSG_PING: 0, MSG_ACK: _ACK.size,
               MSG_STATUS: _STATUS.size, MSG_CLAIM: _CLAIM.size, MSG_HANDOVER: _HANDOVER.size,
               MSG_DRIVE: _DRIVE.size, MSG_OWNER: _OWNER.size, MSG_NACK: _NACK.size, MSG_DRIVEN: _ACK.size + 1}
MESSAGE_NAMES = {MSG_SET_VELOCITY: "SET_VELOCITY", MSG_STOP: "STOP", MSG_PING: "PING", MSG_ACK: "ACK",
                 MSG_STATUS: "STATUS", MSG_CLAIM: "CLAIM", MSG_HANDOVER: "HANDOVER", MSG_DRIVE: "DRIVE",
                 MSG_OWNER: "OWNER", MSG_NACK: "NACK", MSG_DRIVEN: "DRIVEN"}
INT16_MAX = 32767

# -- protocol 3: authenticated frames (docs/follower-protocol.md, "Authenticated frames") ---------
# Any request or reply above, with bit 0x40 set in its type, carries a 15-byte trailer after its
# payload: uint8 id (a request's sender, a reply's asker), uint48 counter (a request's: the
# sender's own, above every one it sent before; a reply's: the counter of the request it answers)
# and an 8-byte SipHash-2-4 tag over bytes 2 .. 5+L-8 (address through the counter), a reply's
# followed by the tag of the request it answers (not sent: both ends have it), so a reply proves
# it answers that very frame. A radio key is 32 bytes: bytes 0..15 sign requests, 16..31 replies
# (a reply can never pass for a request).
AUTH = 0x40
TRAILER = struct.Struct("<B6s8s")
TRAILER_LEN = TRAILER.size  # 15
TAG_LEN = 8
COUNTER_MAX = (1 << 48) - 1
RADIO_KEY_LEN = 32
OPEN_KEY = bytes(RADIO_KEY_LEN)  # no key provisioned: the frames prove only that a reply heard its request
_COUNTS = struct.Struct("<HHHH")  # an authenticated STATUS adds the robot's refusals (see RadioCounts)
for _t, _n in list(PAYLOAD_LEN.items()):
    PAYLOAD_LEN[_t | AUTH] = _n + TRAILER_LEN + (_COUNTS.size if _t == MSG_STATUS else 0)
    MESSAGE_NAMES[_t | AUTH] = MESSAGE_NAMES[_t] + "+MAC"


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: polynomial 0x1021, initial value 0xFFFF, no reflection, no final XOR."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True)
class Frame:
    address: int
    seq: int
    msg_type: int
    payload: bytes = b""


def encode_frame(frame: Frame) -> bytes:
    """The bytes on the wire for one frame; ValueError for fields out of range."""
    if not 0 <= frame.address <= 0xFF or not 0 <= frame.seq <= 0xFF or not 0 <= frame.msg_type <= 0xFF:
        raise ValueError(f"address, sequence and type are bytes (0..255): {frame}")
    if len(frame.payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(frame.payload)} bytes: at most {MAX_PAYLOAD}")
    body = bytes((frame.address, frame.seq, frame.msg_type, len(frame.payload))) + frame.payload
    return SYNC + body + struct.pack("<H", crc16(body))


def _fixed(value: float, scale: float) -> int:
    """A physical value as a saturated int16 in units of 1/scale (NaN -> 0)."""
    if math.isnan(value):
        return 0
    return int(max(-INT16_MAX, min(INT16_MAX, round(value * scale))))


def set_velocity(address: int, seq: int, v_mps: float, w_rps: float) -> Frame:
    """SET_VELOCITY in mm/s and mrad/s (saturated to int16: ±32.767 m/s, ±32.767 rad/s)."""
    return Frame(address, seq, MSG_SET_VELOCITY, _VELOCITY.pack(_fixed(v_mps, 1000.0), _fixed(w_rps, 1000.0)))


def stop(address: int, seq: int) -> Frame:
    return Frame(address, seq, MSG_STOP)


def ping(address: int, seq: int) -> Frame:
    return Frame(address, seq, MSG_PING)


def decode_velocity(frame: Frame) -> tuple[float, float]:
    """(v m/s, w rad/s) of a SET_VELOCITY frame."""
    v, w = _VELOCITY.unpack(frame.payload)
    return v / 1000.0, w / 1000.0


# -- protocol 2: ownership -----------------------------------------------------------------------
def _u16(x: int) -> int:
    return max(0, min(0xFFFF, int(x)))


def claim(address: int, seq: int, leader: int, lease_ms: int) -> Frame:
    return Frame(address, seq, MSG_CLAIM, _CLAIM.pack(leader & 0xFF, _u16(lease_ms)))


def handover(address: int, seq: int, from_leader: int, to_leader: int, lease_ms: int) -> Frame:
    return Frame(address, seq, MSG_HANDOVER, _HANDOVER.pack(from_leader & 0xFF, to_leader & 0xFF, _u16(lease_ms)))


def drive(address: int, seq: int, leader: int, observation_age_ms: int, v_mps: float, w_rps: float) -> Frame:
    """DRIVE: SET_VELOCITY from ``leader``, computed from an observation this old (ms, saturated)."""
    return Frame(address, seq, MSG_DRIVE, _DRIVE.pack(leader & 0xFF, _u16(observation_age_ms),
                                                      _fixed(v_mps, 1000.0), _fixed(w_rps, 1000.0)))


@dataclass(frozen=True)
class Drive:
    leader: int
    observation_age_ms: int
    v_mps: float
    w_rps: float


def decode_drive(frame: Frame) -> Drive:
    leader, age, v, w = _DRIVE.unpack(frame.payload)
    return Drive(leader, age, v / 1000.0, w / 1000.0)


def decode_claim(frame: Frame) -> tuple[int, int]:
    """(leader, lease ms) of a CLAIM."""
    leader, lease = _CLAIM.unpack(frame.payload)
    return leader, lease


def decode_handover(frame: Frame) -> tuple[int, int, int]:
    """(from, to, lease ms) of a HANDOVER."""
    a, b, lease = _HANDOVER.unpack(frame.payload)
    return a, b, lease


@dataclass(frozen=True)
class Ownership:
    """A robot's answer about its owner: OWNER (granted) or NACK (refused, and why), to ``asker``."""

    owner: int  # 0: none
    lease_left_ms: int
    reason: int = 0  # NACK_*; 0 in an OWNER
    asker: int = 0  # the leader whose frame this answers


def owner(address: int, seq: int, o: Ownership) -> Frame:
    return Frame(address, seq, MSG_OWNER, _OWNER.pack(o.owner & 0xFF, _u16(o.lease_left_ms), o.asker & 0xFF))


def nack(address: int, seq: int, o: Ownership) -> Frame:
    return Frame(address, seq, MSG_NACK, _NACK.pack(o.owner & 0xFF, _u16(o.lease_left_ms), o.reason & 0xFF,
                                                    o.asker & 0xFF))


def decode_ownership(frame: Frame) -> Ownership:
    """OWNER or NACK."""
    if frame.msg_type == MSG_OWNER:
        who, left, asker = _OWNER.unpack(frame.payload)
        return Ownership(who, left, 0, asker)
    return Ownership(*_NACK.unpack(frame.payload))


def driven(address: int, seq: int, a: Ack, asker: int) -> Frame:
    """DRIVEN: a DRIVE obeyed (the ACK's odometry), answering leader ``asker``."""
    return Frame(address, seq, MSG_DRIVEN, ack(address, seq, a).payload + bytes((asker & 0xFF,)))


def decode_driven(frame: Frame) -> tuple[Ack, int]:
    """(the odometry, the leader answered) of a DRIVEN."""
    return decode_ack(Frame(frame.address, frame.seq, MSG_ACK, frame.payload[:-1])), frame.payload[-1]


def sender(frame: Frame) -> int | None:
    """The leader a protocol 2 request is from (a CLAIM's or DRIVE's leader, a HANDOVER's
    giver: the first byte of each); None for any other frame, which names nobody."""
    return frame.payload[0] if frame.msg_type in FROM_A_LEADER else None


def answers(frame: Frame) -> int | None:
    """The leader a protocol 2 reply answers (None: a protocol 1 reply, which names nobody)."""
    if frame.msg_type in (MSG_OWNER, MSG_NACK):
        return decode_ownership(frame).asker
    if frame.msg_type == MSG_DRIVEN:
        return frame.payload[-1]
    return None


@dataclass(frozen=True)
class Ack:
    """A robot's answer to SET_VELOCITY / STOP: its wheel-encoder odometry."""

    left_ticks: int
    right_ticks: int
    v_mps: float  # measured by the encoders
    w_rps: float
    flags: int


def ack(address: int, seq: int, a: Ack) -> Frame:
    return Frame(address, seq, MSG_ACK, _ACK.pack(
        _wrap_i32(a.left_ticks), _wrap_i32(a.right_ticks), _fixed(a.v_mps, 1000.0), _fixed(a.w_rps, 1000.0),
        a.flags & 0xFF))


def decode_ack(frame: Frame) -> Ack:
    left, right, v, w, flags = _ACK.unpack(frame.payload)
    return Ack(left, right, v / 1000.0, w / 1000.0, flags)


@dataclass(frozen=True)
class Status:
    """A robot's answer to PING."""

    battery_mv: int
    flags: int
    command_age_ms: int  # saturates at 65535
    uptime_ms: int  # wraps at 2^32


def status(address: int, seq: int, s: Status) -> Frame:
    return Frame(address, seq, MSG_STATUS, _STATUS.pack(
        max(0, min(0xFFFF, s.battery_mv)), s.flags & 0xFF, max(0, min(0xFFFF, s.command_age_ms)),
        s.uptime_ms & 0xFFFFFFFF))


def decode_status(frame: Frame) -> Status:
    return Status(*_STATUS.unpack(frame.payload))


def _wrap_i32(x: int) -> int:
    return ((int(x) + 2**31) % 2**32) - 2**31


@dataclass
class FrameParser:
    """Bytes in (any chunking), valid frames out; never raises, counts what it rejects.

    ``rejected`` counts frames that started with the sync bytes but were refused, by
    reason: ``crc``, ``length`` (over MAX_PAYLOAD, or not the size the type needs),
    ``type`` (unknown message type). ``skipped_bytes`` counts bytes that were not part
    of any frame (noise between frames, the first byte of a refused frame).
    ``last_rejects`` lists (reason, address byte as received) for the frames the last
    ``feed`` refused: the address is unprotected by then, so only a hint.
    """

    buffer: bytearray = field(default_factory=bytearray)
    frames_ok: int = 0
    skipped_bytes: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: {"crc": 0, "length": 0, "type": 0})
    last_rejects: list[tuple[str, int]] = field(default_factory=list)

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def feed(self, data: bytes) -> list[Frame]:
        buf = self.buffer
        buf += data
        out: list[Frame] = []
        rejects: list[tuple[str, int]] = []
        self.last_rejects = rejects
        pos = 0
        n = len(buf)
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                # keep a trailing first sync byte: its partner may come with the next chunk
                keep = n - 1 if n > pos and buf[n - 1] == SYNC[0] else n
                self.skipped_bytes += keep - pos
                pos = keep
                break
            self.skipped_bytes += start - pos
            pos = start
            if n - start < HEADER_LEN:
                break  # wait for the rest of the header
            length = buf[start + 5]
            if length > MAX_PAYLOAD:
                self.rejected["length"] += 1
                rejects.append(("length", buf[start + 2]))
                self.skipped_bytes += 1
                pos = start + 1
                continue
            end = start + HEADER_LEN + length + CRC_LEN
            if n < end:
                break  # wait for the rest of the frame
            body = bytes(buf[start + 2:start + HEADER_LEN + length])
            (crc,) = struct.unpack_from("<H", buf, end - CRC_LEN)
            if crc != crc16(body):
                self.rejected["crc"] += 1
                rejects.append(("crc", body[0]))
                self.skipped_bytes += 1
                pos = start + 1  # the real next frame may start inside this one
                continue
            msg_type = body[2]
            if msg_type not in PAYLOAD_LEN:
                self.rejected["type"] += 1
                rejects.append(("type", body[0]))
            elif PAYLOAD_LEN[msg_type] != length:
                self.rejected["length"] += 1
                rejects.append(("length", body[0]))
            else:
                out.append(Frame(body[0], body[1], msg_type, body[4:]))
                self.frames_ok += 1
            pos = end
        del buf[:pos]
        return out


# -- protocol 3: authenticated frames -----------------------------------------------------------
@dataclass(frozen=True)
class Sealed:
    """An authenticated frame opened: the plain frame inside, who sent it (or whom a reply answers)
    and the counter, and which of the keys tried verified it (0 the current, 1 the next)."""

    frame: Frame
    ident: int
    counter: int
    key_index: int = 0


@dataclass(frozen=True)
class RadioCounts:
    """What an authenticated robot refused (saturating at 65535 on the wire), reported in its STATUS."""

    bad_mac: int = 0  # authenticated frames whose tag no key of the robot's verified
    unknown_sender: int = 0  # a sender the robot was not provisioned with, or a frame naming another leader
    replayed: int = 0  # a counter not above the last one accepted from that sender
    unauthenticated: int = 0  # plain (protocol 1/2) motion, claims and handovers


def is_sealed(frame: Frame) -> bool:
    return bool(frame.msg_type & AUTH)


def _half(key: bytes, msg_type: int) -> bytes:
    if len(key) != RADIO_KEY_LEN:
        raise ValueError(f"a radio key is {RADIO_KEY_LEN} bytes, not {len(key)}")
    return key[:16] if msg_type < 0x80 else key[16:]


def seal(frame: Frame, key: bytes, ident: int, counter: int, request_tag: bytes = b"") -> Frame:
    """The authenticated form of a plain ``frame``: type | AUTH, the payload, then id, counter, tag;
    a reply's tag also covers ``request_tag`` (the tag of the request it answers)."""
    if not 0 <= counter <= COUNTER_MAX or not 0 <= ident <= 0xFF:
        raise ValueError(f"id 0..255 and counter 0..2^48-1: {ident}, {counter}")
    msg_type = frame.msg_type | AUTH
    head = frame.payload + bytes((ident,)) + counter.to_bytes(6, "little")
    signed = bytes((frame.address, frame.seq, msg_type, len(head) + TAG_LEN)) + head
    return Frame(frame.address, frame.seq, msg_type, head + _tag(_half(key, msg_type), signed + request_tag))


def open_sealed(frame: Frame, keys: tuple[bytes, ...], request_tag: bytes = b"") -> Sealed | None:
    """The frame inside an authenticated ``frame`` if one of ``keys`` verifies its tag (a reply's:
    with ``request_tag``, the tag of the request it answers), else None."""
    if not is_sealed(frame) or len(frame.payload) < TRAILER_LEN:
        return None
    body = bytes((frame.address, frame.seq, frame.msg_type, len(frame.payload))) + frame.payload[:-TAG_LEN]
    got = frame.payload[-TAG_LEN:]
    for k, key in enumerate(keys):
        if _tag(_half(key, frame.msg_type), body + request_tag) == got:
            ident, counter, _ = TRAILER.unpack(frame.payload[-TRAILER_LEN:])
            inner = Frame(frame.address, frame.seq, frame.msg_type & ~AUTH, frame.payload[:-TRAILER_LEN])
            return Sealed(inner, ident, int.from_bytes(counter, "little"), k)
    return None


def tag_of(frame: Frame) -> bytes:
    """An authenticated frame's tag (its last 8 bytes)."""
    return frame.payload[-TAG_LEN:]


def trailer(frame: Frame) -> tuple[int, int]:
    """(id, counter) an authenticated frame says it carries, unverified (for matching only)."""
    ident, counter, _ = TRAILER.unpack(frame.payload[-TRAILER_LEN:])
    return ident, int.from_bytes(counter, "little")


def status_counts(status_payload: bytes, c: RadioCounts) -> bytes:
    """An authenticated STATUS's payload: the STATUS's 9 bytes, then the robot's refusal counts."""
    def u16(x: int) -> int:
        return max(0, min(0xFFFF, x))

    return status_payload + _COUNTS.pack(u16(c.bad_mac), u16(c.unknown_sender), u16(c.replayed),
                                         u16(c.unauthenticated))


def decode_status_counts(frame: Frame) -> tuple[Status, RadioCounts]:
    """(STATUS, refusal counts) of an opened authenticated STATUS."""
    return Status(*_STATUS.unpack(frame.payload[:_STATUS.size])), RadioCounts(*_COUNTS.unpack(frame.payload[_STATUS.size:]))
