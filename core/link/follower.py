"""What a follower's firmware does with the link's frames: differential drive, encoders, watchdog.

Pure functions on a frozen state, so the same rules are tested here and run by the
emulator (`omniformation emulate-follower`) behind a real pseudo-terminal. The rules are
those of docs/follower-protocol.md:

* SET_VELOCITY sets the wheel targets (v ± w·b/2, both scaled together at the motors' limit)
  and resets the command age;
* STOP sets them to zero at once and raises FLAG_STOPPED until the next SET_VELOCITY;
* a command older than WATCHDOG_S sets them to zero and raises FLAG_WATCHDOG;
* PING only answers with STATUS (it does not feed the watchdog);
* a broadcast frame is obeyed and never answered (robots would collide on a shared radio);
* protocol 2, ownership: the robot holds an owner (a leader's number) and a lease. Only the
  owner's DRIVE moves it while the lease lives (each one renews it); anyone else's motion is
  refused with a NACK naming the owner; a CLAIM is granted when no lease lives (the owner
  went quiet) or to the owner itself, a HANDOVER only from the owner; a DRIVE computed from an
  observation older than MAX_OBSERVATION_AGE_MS stops the robot and is refused. STOP is
  obeyed from anyone (stopping is always safe). firmware/omni_follower.c does the same
  (tests/app/backends/test_firmware.py holds the two to one script).
* protocol 3, a radio key provisioned (:class:`RadioAuth`): only authenticated frames
  (core.link.protocol.seal) move, claim or hand the robot over: a tag no key verifies, a sender
  the robot does not know, a counter not above the last one taken from that sender, or a plain
  frame of protocol 1/2 is refused without a word and counted (``refusals``, in the STATUS). The
  replies are authenticated with the same key and carry the request's counter, so they prove
  they answer that very frame. STOP follows the provisioned policy (docs/safety.md). With a key
  per leader (``RadioAuth.leader_keys``) a frame is checked only against the keys of the id it
  carries: a leader's key signs as its own id alone (another's id: bad MAC).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from core.link import protocol as p


@dataclass(frozen=True)
class FollowerHardware:
    """A small differential-drive robot like the paper's (15 x 25 cm, gear motors)."""

    wheel_base_m: float = 0.12
    wheel_radius_m: float = 0.03
    ticks_per_rev: int = 360
    motor_tau_s: float = 0.12  # first-order lag of each wheel's speed
    wheel_speed_max_mps: float = 0.45
    battery_mv: int = 7400

    @property
    def metres_per_tick(self) -> float:
        return 2 * math.pi * self.wheel_radius_m / self.ticks_per_rev


@dataclass(frozen=True)
class FollowerState:
    address: int
    target_l_mps: float = 0.0
    target_r_mps: float = 0.0
    wheel_l_mps: float = 0.0
    wheel_r_mps: float = 0.0
    dist_l_m: float = 0.0  # wheel travel since power-on (the encoders count it in ticks)
    dist_r_m: float = 0.0
    command_age_s: float = math.inf  # since the last valid SET_VELOCITY
    flags: int = p.FLAG_WATCHDOG  # at power-on nothing has been commanded
    uptime_s: float = 0.0
    # protocol 2: who owns the robot (a leader's number, 0: nobody) and for how much longer
    owner: int = 0
    lease_ms: int = 0  # the lease granted (each DRIVE of the owner renews it)
    lease_left_s: float = 0.0
    driven_by: int = 0  # the leader whose DRIVE the robot obeyed last
    driven_age_s: float = math.inf
    two_owners: int = 0  # DRIVEs obeyed from a leader within 100 ms of another's (never expected)
    nacks: int = 0
    # protocol 3: the last counter taken from each sender (at most MAX_SENDERS), and what was refused
    counters: tuple[tuple[int, int], ...] = ()
    refusals: p.RadioCounts = p.RadioCounts()

    @property
    def lease_lives(self) -> bool:
        return self.owner != 0 and self.lease_left_s > 0.0

    def ownership(self, reason: int = 0, asker: int = 0) -> p.Ownership:
        left = int(round(self.lease_left_s * 1000)) if self.lease_lives else 0
        return p.Ownership(self.owner, left, reason, asker)

    def ticks(self, hw: FollowerHardware) -> tuple[int, int]:
        return int(math.floor(self.dist_l_m / hw.metres_per_tick)), int(math.floor(self.dist_r_m / hw.metres_per_tick))

    def measured(self, hw: FollowerHardware) -> tuple[float, float]:
        """(v m/s, w rad/s) from the wheel speeds, as the encoders see them."""
        return (self.wheel_l_mps + self.wheel_r_mps) / 2, (self.wheel_r_mps - self.wheel_l_mps) / hw.wheel_base_m

    @property
    def moving(self) -> bool:
        return abs(self.wheel_l_mps) > 1e-4 or abs(self.wheel_r_mps) > 1e-4


def wheel_targets(v: float, w: float, hw: FollowerHardware) -> tuple[float, float]:
    """(left, right) m/s for body velocity (v, w): v ∓ w·b/2, and if the faster wheel is over
    the motors' limit both are scaled by the same factor, so the robot keeps its path's
    curvature and only goes slower (docs/follower-protocol.md)."""
    half = w * hw.wheel_base_m / 2
    left, right = v - half, v + half
    big = max(abs(left), abs(right))
    if big > hw.wheel_speed_max_mps:
        k = hw.wheel_speed_max_mps / big
        left, right = left * k, right * k
    return left, right


def step_follower(s: FollowerState, hw: FollowerHardware, dt: float) -> FollowerState:
    """Advance the motors and encoders by dt seconds; the watchdog acts here."""
    age = s.command_age_s + dt
    tl, tr, flags = s.target_l_mps, s.target_r_mps, s.flags
    if age > p.WATCHDOG_S and not flags & p.FLAG_WATCHDOG:
        tl, tr, flags = 0.0, 0.0, flags | p.FLAG_WATCHDOG
    k = 1.0 - math.exp(-dt / hw.motor_tau_s) if hw.motor_tau_s > 0 else 1.0
    wl = s.wheel_l_mps + k * (tl - s.wheel_l_mps)
    wr = s.wheel_r_mps + k * (tr - s.wheel_r_mps)
    if tl == 0.0 and abs(wl) < 1e-4:
        wl = 0.0
    if tr == 0.0 and abs(wr) < 1e-4:
        wr = 0.0
    return dataclasses.replace(
        s, target_l_mps=tl, target_r_mps=tr, wheel_l_mps=wl, wheel_r_mps=wr,
        dist_l_m=s.dist_l_m + (s.wheel_l_mps + wl) / 2 * dt, dist_r_m=s.dist_r_m + (s.wheel_r_mps + wr) / 2 * dt,
        command_age_s=age, flags=flags, uptime_s=s.uptime_s + dt, lease_left_s=max(0.0, s.lease_left_s - dt),
        driven_age_s=s.driven_age_s + dt)


TWO_OWNERS_S = 0.1  # two leaders' DRIVEs obeyed closer together than this: one robot with two owners


def _obey(s: FollowerState, hw: FollowerHardware, v: float, w: float) -> FollowerState:
    """A motion command taken (SET_VELOCITY, or the owner's DRIVE): the wheels' targets, the
    watchdog fed, WATCHDOG and STOPPED cleared."""
    left, right = wheel_targets(v, w, hw)
    return dataclasses.replace(s, target_l_mps=left, target_r_mps=right, command_age_s=0.0,
                               flags=s.flags & ~(p.FLAG_WATCHDOG | p.FLAG_STOPPED))


def _odometry(s: FollowerState, hw: FollowerHardware) -> p.Ack:
    """What an ACK (and a DRIVEN) carries: the encoder counts and the velocity they measure."""
    left, right = s.ticks(hw)
    v_meas, w_meas = s.measured(hw)
    return p.Ack(left, right, v_meas, w_meas, s.flags)


def _ownership(s: FollowerState, hw: FollowerHardware, frame: p.Frame) -> tuple[FollowerState, p.Frame | None]:
    """CLAIM, HANDOVER and DRIVE (protocol 2), and a protocol 1 SET_VELOCITY to an owned robot."""
    asker = p.sender(frame) or 0

    def refuse(reason: int) -> tuple[FollowerState, p.Frame | None]:
        r = dataclasses.replace(s, nacks=s.nacks + 1)
        return r, p.nack(s.address, frame.seq, s.ownership(reason, asker))

    def grant(leader: int, lease_ms: int) -> tuple[FollowerState, p.Frame | None]:
        lease = max(p.LEASE_MIN_MS, min(p.LEASE_MAX_MS, lease_ms))
        r = s if leader == s.owner else dataclasses.replace(s, target_l_mps=0.0, target_r_mps=0.0)  # from rest
        r = dataclasses.replace(r, owner=leader, lease_ms=lease, lease_left_s=lease / 1000)
        return r, p.owner(s.address, frame.seq, r.ownership(0, asker))

    if frame.msg_type == p.MSG_SET_VELOCITY:  # protocol 1: only a robot nobody holds takes it
        return refuse(p.NACK_NOT_OWNER)
    if frame.msg_type == p.MSG_CLAIM:
        leader, lease = p.decode_claim(frame)
        if not 1 <= leader <= p.MAX_LEADER:
            return refuse(p.NACK_NOT_OWNER)
        if s.lease_lives and s.owner != leader:
            return refuse(p.NACK_OWNED)
        return grant(leader, lease)
    if frame.msg_type == p.MSG_HANDOVER:
        frm, to, lease = p.decode_handover(frame)
        if s.owner == 0 or frm != s.owner or not 1 <= to <= p.MAX_LEADER:
            return refuse(p.NACK_NOT_OWNER)
        return grant(to, lease)
    d = p.decode_drive(frame)
    if not s.lease_lives or d.leader != s.owner:
        return refuse(p.NACK_NOT_OWNER)
    if d.observation_age_ms > p.MAX_OBSERVATION_AGE_MS:  # what it was computed from is gone: stand still
        s = dataclasses.replace(s, target_l_mps=0.0, target_r_mps=0.0)
        return refuse(p.NACK_STALE)
    two = s.driven_by not in (0, d.leader) and s.driven_age_s < TWO_OWNERS_S
    s = dataclasses.replace(_obey(s, hw, d.v_mps, d.w_rps), lease_left_s=s.lease_ms / 1000, driven_by=d.leader,
                            driven_age_s=0.0, two_owners=s.two_owners + two)
    return s, p.driven(s.address, frame.seq, _odometry(s, hw), d.leader)


STOP_ANYONE = "anyone"  # every STOP heard stops the robot, authenticated or not (fail-safe; the default)
STOP_AUTHENTICATED = "authenticated"  # only an authenticated, fresh STOP from a known leader
STOP_POLICIES = (STOP_ANYONE, STOP_AUTHENTICATED)
MAX_SENDERS = 16  # leaders a robot keeps a counter for (the firmware's table)


@dataclass(frozen=True)
class RadioAuth:
    """What a robot is provisioned with for protocol 3 (`omniformation radio-provision`)."""

    keys: tuple[bytes, ...] = (p.OPEN_KEY,)  # the current key, then the next one during a rotation
    leaders: tuple[int, ...] = ()  # the leaders' radio ids it obeys; empty: any 1..250 (first MAX_SENDERS seen)
    stop: str = STOP_ANYONE
    # a key per leader (aligned with ``leaders``; current, then next): a frame is checked only
    # against the keys of the id it carries, so a leader's key signs as its own id alone and
    # ``keys`` serves nobody. Empty: ``keys`` verify every sender (one key for the fleet).
    leader_keys: tuple[tuple[bytes, ...], ...] = ()

    def keys_of(self, ident: int) -> tuple[bytes, ...]:
        """The keys that may verify a frame carrying sender ``ident`` (none: an unknown sender)."""
        if not self.leader_keys:
            return self.keys
        return self.leader_keys[self.leaders.index(ident)] if ident in self.leaders else ()


def _refused(s: FollowerState, kind: str) -> FollowerState:
    c = s.refusals
    return dataclasses.replace(s, refusals=dataclasses.replace(c, **{kind: getattr(c, kind) + 1}))


def _stopped(s: FollowerState) -> FollowerState:
    return dataclasses.replace(s, target_l_mps=0.0, target_r_mps=0.0, flags=s.flags | p.FLAG_STOPPED)


REFUSED_PLAIN = (p.MSG_SET_VELOCITY, p.MSG_CLAIM, p.MSG_HANDOVER, p.MSG_DRIVE, p.MSG_STOP)


def handle_frame(s: FollowerState, hw: FollowerHardware, frame: p.Frame,
                 auth: RadioAuth | None = None) -> tuple[FollowerState, p.Frame | None]:
    """Obey one frame addressed to this robot (or broadcast); return the new state and the reply.
    ``auth``: protocol 3 (authenticated frames only); None: a protocol 2 robot."""
    if auth is None:
        return _handle_plain(s, hw, frame)
    if frame.address not in (s.address, p.BROADCAST) or frame.msg_type & 0x80:
        return s, None  # another robot's business, or a reply
    kind = frame.msg_type & ~p.AUTH
    fail_safe = kind == p.MSG_STOP and auth.stop == STOP_ANYONE  # this STOP stops, whatever else is wrong
    if not p.is_sealed(frame):
        if fail_safe:
            return _stopped(s), None  # obeyed, never answered
        return (_refused(s, "unauthenticated") if kind in REFUSED_PLAIN else s), None
    keys = auth.keys_of(p.trailer(frame)[0]) if len(frame.payload) >= p.TRAILER_LEN else auth.keys
    opened = p.open_sealed(frame, keys) if keys else None
    why = ""
    if opened is None:
        why = "bad_mac"  # with a key per leader, an id with none: no key of the robot's verifies it
    else:
        named = p.sender(opened.frame)
        slots = dict(s.counters)
        known = opened.ident in auth.leaders if auth.leaders else 1 <= opened.ident <= p.MAX_LEADER
        if not known or (named is not None and named != opened.ident) or \
                (opened.ident not in slots and len(slots) >= MAX_SENDERS):
            why = "unknown_sender"
        elif opened.counter <= slots.get(opened.ident, -1):
            why = "replayed"
    if why or opened is None:
        s = _refused(s, why)
        return (_stopped(s) if fail_safe else s), None
    slots[opened.ident] = opened.counter
    s = dataclasses.replace(s, counters=tuple(sorted(slots.items())))
    s, reply = _handle_plain(s, hw, opened.frame)
    if reply is None:
        return s, None
    if reply.msg_type == p.MSG_STATUS:
        reply = p.Frame(reply.address, reply.seq, reply.msg_type, p.status_counts(reply.payload, s.refusals))
    return s, p.seal(reply, keys[opened.key_index], opened.ident, opened.counter, p.tag_of(frame))


def _handle_plain(s: FollowerState, hw: FollowerHardware, frame: p.Frame) -> tuple[FollowerState, p.Frame | None]:
    """Protocols 1 and 2 (and the frame inside an authenticated one)."""
    if frame.address not in (s.address, p.BROADCAST):
        return s, None
    if frame.msg_type in p.FROM_A_LEADER or (frame.msg_type == p.MSG_SET_VELOCITY and s.lease_lives):
        if frame.address == p.BROADCAST:
            return s, None  # ownership is one robot's business: never by broadcast, never answered
        return _ownership(s, hw, frame)
    if frame.msg_type == p.MSG_SET_VELOCITY:
        s = _obey(s, hw, *p.decode_velocity(frame))
    elif frame.msg_type == p.MSG_STOP:
        s = _stopped(s)
    elif frame.msg_type != p.MSG_PING:
        return s, None  # replies from other robots on a shared line: not for us
    if frame.address == p.BROADCAST:
        return s, None
    if frame.msg_type == p.MSG_PING:
        age_ms = 0xFFFF if math.isinf(s.command_age_s) else int(min(0xFFFF, s.command_age_s * 1000))
        return s, p.status(s.address, frame.seq, p.Status(hw.battery_mv, s.flags, age_ms, int(s.uptime_s * 1000)))
    return s, p.ack(s.address, frame.seq, _odometry(s, hw))
