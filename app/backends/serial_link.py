"""The follower link over a serial port (cable, USB-serial, or a radio dongle): pyserial.

One port serves every follower (addressed frames, as on a shared radio); give one
``SerialLink`` per port for one port per follower. ``send`` is called by the loop once
per tick: it writes one SET_VELOCITY per follower (zero when stopped, which also feeds
their watchdogs) and returns at once; a reader thread parses the replies and keeps, per
follower, the round-trip time, the encoder odometry and the status (battery, watchdog).

The link tells the truth. A reply counts only when it matches a frame we sent: the same
address and sequence, and the type that answers it (ACK for SET_VELOCITY and STOP, STATUS for
PING). Our own frames coming back (an echoing line or a loopback plug) are recognised as
echoes, and a well-formed reply that answers nothing we sent is counted as unmatched; neither
makes the link "ok". Per follower, every SET_VELOCITY written is exactly one of: answered
(in time), late (answered after ``REPLY_TIMEOUT_S``), lost (never answered) or still pending,
so ``sent == answered + late + lost + pending`` at every moment. A frame that could not be written
is not sent; one answered before its write's timeout fired was written.

A robot is alive only while it answers in time: a reply counts as an answer when it matches a
frame sent within ``REPLY_TIMEOUT_S`` and arrives within it. Late replies, replies to frames whose
write failed long ago and replies that answer nothing we sent show the robot is there but say
nothing about now: they never make it (or the link) alive. Per robot, ``answering()`` is true only
while its last two answers are each within the timeout of the one before and of now (one reply
that happens to match a sequence number, as from a robot stuck repeating an old one, is not
enough); a robot that is not answering is sent zero whatever the loop asks, and the loop counts it
untracked. A robot that only ever answers late is "silent", and a link with no robot answering in
time is "link lost", never "degraded".

State for people and for the loop: "ok" while every follower answers; "degraded" when one
is silent or loses more than ``DEGRADED_LOSS`` of its recent replies; "link lost" when the
port is closed or no follower has answered for ``SILENT_S``. While the link is lost the
link commands zero whatever it is given (the loop does too), and a reopened port gets STOP
for every follower before anything else. A port that fails is reopened with back-off (0.25 s
doubling to 2 s) without ever blocking the loop.

Every frame is authenticated (protocol 3; the counter and the replies' check: app.backends.link_auth, docs/follower-protocol.md, "Authenticated frames"):
it carries this leader's radio id, a counter above every one it sent before and a SipHash-2-4 tag
under the radio key (the open key when none is given: on a cable that proves nothing about who
sent it, but a reply still has to carry the request's counter under a valid tag, so a device that
answers without hearing the frame, or answers an older one, never counts as answering). A reply
counts only when its tag verifies under the key and it names this leader and the counter of a
frame we sent. A robot that answers only protocol 1 or 2 (a plain STATUS to a plain PING, and
nothing authenticated) is named ("F2 speaks an unauthenticated protocol") and not driven unless
``allow_unauthenticated``, which the link state then says on every tick.

Every command is clamped again here to the limits given (defence in depth: the controller
already clamps), NaN becomes 0, and ``close`` sends STOP to every follower.
"""

from __future__ import annotations

import errno
import math
import os
import threading
import time
from collections import OrderedDict
from typing import Any
from collections.abc import Callable

import numpy as np
import serial

from core.link import protocol as p
from core.types import Commands, FloatArray

from app.backends.link_auth import ALLOWED_NOTE, UNAUTHENTICATED, FrameCounter, ReplyAuth
from app.backends.link_stats import QUALITY_WINDOW, FollowerLinkStats

__all__ = ["ALLOWED_NOTE", "QUALITY_WINDOW", "REPLY_TIMEOUT_S", "UNAUTHENTICATED", "FollowerLinkStats", "FrameCounter",
           "PortPerFollowerLink", "SerialLink", "make_link"]

REPLY_TIMEOUT_S = 0.25  # a SET_VELOCITY not answered by then counts as a lost reply
SILENT_S = 0.5  # no reply at all for this long: "link lost"
# pyserial raises its write timeout whenever a write call took longer than the timeout, even
# when every byte went out (a thread held off the CPU for 50 ms): one timed-out write is not
# a dead port. This many in a row is (the port takes no bytes): closed and reopened.
STALLED_WRITES_LOST = 3
ODOMETRY_STALE_S = 0.2  # measured velocities older than this are taken as zero
PING_PERIOD_S = 1.0  # each follower's STATUS (battery, watchdog) is asked for this often
BACKOFF_S = (0.25, 2.0)
DEGRADED_LOSS = 0.2  # more than this share of a follower's recent commands unanswered: "degraded"
EXPIRED_KEPT = 1024  # unanswered (address, sequence) pairs remembered, so a late reply is known as late
# what answers each frame of ours (protocol 2's CLAIM and DRIVE: docs/follower-protocol.md, "Ownership")
REPLIES = {p.MSG_SET_VELOCITY: (p.MSG_ACK,), p.MSG_STOP: (p.MSG_ACK,), p.MSG_PING: (p.MSG_STATUS,),
           p.MSG_CLAIM: (p.MSG_OWNER, p.MSG_NACK), p.MSG_DRIVE: (p.MSG_DRIVEN, p.MSG_NACK)}
MOTION = (p.MSG_SET_VELOCITY, p.MSG_DRIVE)  # the frames counted as sent (one per robot per tick)
LEASE_MS = 1000  # with a radio id: the lease asked for; each DRIVE renews it
CLAIM_RETRY_S = 0.5  # a robot another leader holds is asked again this often (its lease may have lapsed)


class SerialLink:
    """A FollowerLink to ``n`` followers at addresses 1..n on one serial port (or to the
    leader base at address 0: the LeaderOdometry port, see app.backends.hardware)."""

    def __init__(self, port: str, n: int, baud: int = 115200, v_max: float = 0.3, w_max: float = 2.0,
                 clock: Callable[[], float] = time.monotonic,
                 opener: Callable[..., Any] | None = None, addresses: list[int] | None = None,
                 radio_id: int | None = None, radio_key: bytes | None = None, sender_id: int | None = None,
                 allow_unauthenticated: bool = False, counter: FrameCounter | None = None) -> None:
        """``addresses``: instead of 1..n, e.g. [0] for the leader base (docs/follower-protocol.md).
        ``radio_id``: this leader's number on a radio other leaders share (1..250): protocol 2,
        it claims its robots, drives only those it owns (DRIVE, with the observation's age) and
        STOPs only those; without it, protocol 1 (one leader on the line). ``radio_key``: the fleet's
        32-byte radio key (None: the open key); ``sender_id``: the id its frames carry (default the
        radio id, else 1); ``allow_unauthenticated``: drive robots that speak only protocol 1/2."""
        self.radio_id = radio_id
        self.radio_key = radio_key if radio_key is not None else p.OPEN_KEY
        self.sender_id = sender_id if sender_id is not None else (radio_id or 1)
        self.allow_unauthenticated = allow_unauthenticated
        self._counter = counter or FrameCounter()
        self.on_owned: Callable[[int], None] | None = None  # told (in the reader) of each robot granted to us
        self.port_name = port
        self.baud = baud
        self.v_max, self.w_max = v_max, w_max
        self.addresses = list(addresses) if addresses is not None else list(range(1, n + 1))
        self.stats = [FollowerLinkStats(a) for a in self.addresses]
        self._by_addr = {s.address: s for s in self.stats}
        self.parser = p.FrameParser()
        self._clock = clock
        self._opener = opener or (lambda: open_port(port, baud))
        self._port: Any = None
        self._lock = threading.Lock()  # guards _port, _pending, stats
        self._pending: dict[tuple[int, int, int], float] = {}  # (address, sequence, request type) -> time written
        self._expired: OrderedDict[tuple[int, int, int], None] = OrderedDict()  # given up on: a reply now is late
        self._unsent: OrderedDict[tuple[int, int, int], float] = OrderedDict()  # failed writes (maybe went out) -> when
        self._tags: OrderedDict[int, bytes] = OrderedDict()  # counter -> tag of the request sent with it
        self._auth = ReplyAuth(self.radio_id, self.sender_id, self.radio_key, self._tags)  # whose a reply is
        self._seq = 0
        self._stop_first = True  # a fresh port gets STOP for everyone before anything else
        self._next_ping = 0.0
        self._ping_index = 0
        self._stop = threading.Event()
        self._opened_at = -math.inf
        self.reason = "connecting"
        self.connects = 0
        self._stalled_writes = 0  # timed-out writes in a row (see STALLED_WRITES_LOST)
        self._thread = threading.Thread(target=self._read_loop, name="omniformation-serial", daemon=True)
        self._thread.start()

    @property
    def n(self) -> int:
        return len(self.addresses)

    # -- state for people ---------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """The port is open and some follower answered a frame of ours within ``SILENT_S``."""
        now = self._clock()
        with self._lock:
            if self._port is None:
                return False
            return any(_alive(s, now, SILENT_S) for s in self.stats)

    @property
    def lost(self) -> bool:
        """No follower answers (or the port is closed): the loop commands zero."""
        return not self.connected

    @property
    def pending(self) -> int:
        with self._lock:
            return self._motion_pending()

    def tally(self) -> tuple[int, int, int]:
        """(sent, answered + late + lost, pending) at one moment: ``sent`` is always the other two's
        sum. Read one by one, the reader's thread may settle a frame in between (a loaded machine)."""
        with self._lock:
            return (sum(s.sent for s in self.stats), sum(s.answered + s.late + s.lost for s in self.stats),
                    self._motion_pending())

    def _motion_pending(self) -> int:
        """Motion frames written and not yet settled (the lock held)."""
        return sum(1 for key in self._pending if key[2] in MOTION)

    def quality(self) -> list[str]:
        """Per follower: "" when it answers well, else why not ("silent 1.2 s", "37 % lost")."""
        now = self._clock()
        out = []
        with self._lock:
            for s in self.stats:
                age = now - s.last_reply
                recent = list(s.recent)
                loss = 1.0 - sum(recent) / len(recent) if recent else 0.0
                if s.legacy and not self.allow_unauthenticated:
                    out.append(UNAUTHENTICATED)
                elif self.radio_id is not None and not s.owned and not s.legacy:
                    out.append(f"owned by leader {s.owner}" if s.owner and s.owner != self.radio_id else "not claimed yet")
                elif not _alive(s, now, SILENT_S):
                    out.append("never answered" if not math.isfinite(age) else f"silent {age:.1f} s")
                elif len(recent) >= QUALITY_WINDOW // 2 and loss > DEGRADED_LOSS:
                    out.append(f"{loss * 100:.0f} % lost")
                else:
                    out.append("")
        return out

    @property
    def link_state(self) -> str:
        state = self._link_state()
        return state + ALLOWED_NOTE if self.allow_unauthenticated else state

    def _link_state(self) -> str:
        if self.radio_id is not None and self._port is not None and not any(s.owned for s in self.stats):
            heard = self._clock() - max((s.last_reply for s in self.stats), default=-math.inf) < 4 * CLAIM_RETRY_S
            if heard:  # the robots answer, and another leader holds every one: this one waits
                return f"serial {self.port_name}: owns no robot yet ({', '.join(f'{_name(s.address)} {why}' for s, why in zip(self.stats, self.quality()))})"
        if not self.connected:
            with self._lock:
                echoes = sum(s.echoes for s in self.stats)
                unmatched = sum(s.unmatched for s in self.stats)
                reason = self.reason
            if self._port is not None and echoes:
                reason += f"; {echoes} of our own frames came back: an echoing line, no robot answers"
            elif self._port is not None and unmatched:
                reason += f"; {unmatched} replies answered nothing we sent"
            return f"link lost ({reason})"
        bad = [f"{_name(s.address)} {why}" for s, why in zip(self.stats, self.quality()) if why]
        if bad:
            return f"serial {self.port_name}: degraded ({', '.join(bad)})"
        return f"serial {self.port_name}: ok"

    def detail(self) -> str:
        """Per follower: round trip, lost replies, CRC errors, battery, watchdog."""
        now = self._clock()
        parts = []
        with self._lock:
            for s in self.stats:
                age = now - s.last_reply
                flags = ("watchdog " if s.flags & p.FLAG_WATCHDOG else "") + ("stopped " if s.flags & p.FLAG_STOPPED else "") \
                    + ("LOW BATTERY " if s.flags & p.FLAG_LOW_BATTERY else "")
                parts.append(f"{_name(s.address)} rtt {s.rtt_mean_ms:.1f} ms, answered {s.answered}/{s.sent},"
                             f" late {s.late}, lost {s.lost}, crc {s.crc_errors}, "
                             f"{s.battery_mv / 1000:.2f} V" + (f", {flags.strip()}" if flags else "")
                             + (f", silent {age:.1f} s" if age > SILENT_S and math.isfinite(age) else "")
                             + (f", forged replies {s.forged}" if s.forged else "")
                             + (", refused " + ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in
                                                         vars(s.refusals).items() if v) if any(vars(s.refusals).values())
                                else ""))
        return "; ".join(parts)

    def answering(self) -> np.ndarray:
        """(n,) bool per robot: its last two answers came in time, the last one within the reply
        timeout of now (and, with a radio id, this leader owns it). Only such a robot is sent
        anything but zero."""
        now = self._clock()
        with self._lock:
            return np.array([self._answering(s, now) for s in self.stats], dtype=bool)

    def answering_at(self, addresses: list[int]) -> np.ndarray:
        """:meth:`answering` for these robots (False for one not on this link)."""
        now = self._clock()
        with self._lock:
            return np.array([a in self._by_addr and self._answering(self._by_addr[a], now) for a in addresses],
                            dtype=bool)

    def _answering(self, s: FollowerLinkStats, now: float) -> bool:
        if s.legacy and not self.allow_unauthenticated:
            return False
        return _alive(s, now, REPLY_TIMEOUT_S) and (self.radio_id is None or s.owned)

    # -- robots taken in and let go (a fleet on a radio: app.backends.arena) -----------------
    def want(self, address: int) -> None:
        """Add robot ``address`` to this link: with a radio id it is claimed at the next send and
        every CLAIM_RETRY_S until granted (an orphan whose lease has not lapsed yet)."""
        with self._lock:
            if address not in self._by_addr:
                s = FollowerLinkStats(address)
                self.stats.append(s)
                self._by_addr[address] = s
                self.addresses.append(address)

    def let_go(self, address: int) -> None:
        """Robot ``address`` leaves this link: nothing more is sent to it (its lease lapses)."""
        with self._lock:
            s = self._by_addr.pop(address, None)
            if s is not None:
                self.stats.remove(s)
                self.addresses.remove(address)

    def owns(self, address: int) -> bool:
        """With a radio id: the robot granted this leader's claim and has not refused it since."""
        with self._lock:
            s = self._by_addr.get(address)
            return s is not None and s.owned

    def measured(self) -> tuple[FloatArray, FloatArray]:
        """(v, w) per follower from the encoders; zero where the odometry is stale."""
        now = self._clock()
        with self._lock:
            fresh = np.array([now - s.last_reply < ODOMETRY_STALE_S for s in self.stats])
            v = np.array([s.v_meas for s in self.stats])
            w = np.array([s.w_meas for s in self.stats])
        return np.where(fresh, v, 0.0), np.where(fresh, w, 0.0)

    # -- FollowerLink ---------------------------------------------------------------------
    def send(self, commands: Commands, addresses: list[int] | None = None) -> None:
        """One SET_VELOCITY per follower (clamped; zero while the link is lost), written without
        blocking the loop. A fresh port gets STOP for everyone first. ``addresses``: the robot
        each command is for (default: the link's robots in order); a robot of the link given no
        command is sent zero (with a radio id: held still, its lease kept)."""
        v = np.clip(np.nan_to_num(np.asarray(commands.v, dtype=float)), -self.v_max, self.v_max)
        w = np.clip(np.nan_to_num(np.asarray(commands.w, dtype=float)), -self.w_max, self.w_max)
        if self.lost:  # nobody answers: nothing but zero goes out (it also asks for replies)
            v, w = np.zeros_like(v), np.zeros_like(w)
        now = self._clock()
        with self._lock:
            order = self.addresses if addresses is None else addresses
            given = {a: (float(v[k]), float(w[k])) for k, a in enumerate(order) if k < len(v) and k < len(w)}
            port = self._port
            if port is None:
                return  # nothing written, nothing sent
            out = bytearray()
            if self._stop_first:
                self._stop_first = False
                out += self._stop_frames()
            seq = self._next_seq()
            keys: list[tuple[int, int, int]] = []
            for s in self.stats:
                # a robot that does not answer gets zero until it does
                vi, wi = given.get(s.address, (0.0, 0.0)) if self._answering(s, now) else (0.0, 0.0)
                if s.legacy and not self.allow_unauthenticated:
                    continue  # never driven; only the PINGs below go to it
                if self.radio_id is None:
                    self._put(out, keys, s, p.set_velocity(s.address, seq, vi, wi))
                elif s.owned:
                    age_ms = _age_ms(commands.observed_at, now, vi, wi)
                    self._put(out, keys, s, p.drive(s.address, seq, self.radio_id, age_ms, vi, wi))
                elif now >= s.next_claim:  # not ours (yet): ask; granted once nobody's lease lives
                    s.next_claim = now + CLAIM_RETRY_S
                    self._put(out, keys, s, p.claim(s.address, seq, self.radio_id, LEASE_MS))
            if now >= self._next_ping and self.stats:
                s = self.stats[self._ping_index % len(self.stats)]
                self._ping_index += 1
                self._put(out, keys, s, p.ping(s.address, seq))
                if not s.authenticated and not s.legacy:  # an older robot answers only a plain PING
                    out += p.encode_frame(p.ping(s.address, seq))
                    keys.append((s.address, seq, p.MSG_PING))
                self._next_ping = now + PING_PERIOD_S / len(self.stats)
            for key in keys:  # registered before the write: a reply can beat the write's return
                self._pending[key] = now
            self._expire(now)
        written = self._write(port, bytes(out))
        with self._lock:
            for key in keys:
                if not written and self._pending.pop(key, None) is not None:
                    # a timed-out write may still have gone out: its reply is ours, not a stranger's
                    self._unsent[key] = now
                elif key[2] in MOTION:  # written, or answered before the write's timeout fired: it went out
                    self._by_addr[key[0]].sent += 1
            while len(self._unsent) > EXPIRED_KEPT:
                self._unsent.popitem(last=False)

    def _put(self, out: bytearray, keys: list[tuple[int, int, int]], s: FollowerLinkStats, frame: p.Frame) -> None:
        """Append one request for robot ``s``, authenticated (plain only to a robot known to speak
        protocol 1/2 while that is allowed), and the key its answer will be matched by."""
        if s.legacy:
            out += p.encode_frame(frame)
            keys.append((s.address, frame.seq, frame.msg_type))
            return
        counter = self._counter.next()
        sealed = p.seal(frame, self.radio_key, self.sender_id, counter)
        out += p.encode_frame(sealed)
        keys.append((s.address, counter, frame.msg_type))
        self._tags[counter] = p.tag_of(sealed)  # its answer's tag covers it
        while len(self._tags) > 2 * EXPIRED_KEPT:
            self._tags.popitem(last=False)

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _stop_frames(self) -> bytes:
        """STOP to every follower, addressed (answered) and broadcast (for robots we do not know).
        On a shared radio (a radio id) only to the robots this leader owns: the others are
        other leaders' to stop."""
        seq = self._next_seq()
        now = self._clock()
        mine = [s for s in self.stats if self.radio_id is None or s.owned]
        out = bytearray()
        keys: list[tuple[int, int, int]] = []
        for s in mine:
            self._put(out, keys, s, p.stop(s.address, seq))
        for key in keys:
            self._pending[key] = now  # its ACK is an answer, not a stranger
        if self.radio_id is None:  # robots we do not know: authenticated, and plain for older ones
            out += p.encode_frame(p.seal(p.stop(p.BROADCAST, seq), self.radio_key, self.sender_id, self._counter.next()))
            out += p.encode_frame(p.stop(p.BROADCAST, seq))
        return bytes(out)

    def stop_all(self) -> None:
        """STOP to every follower now."""
        with self._lock:
            data = self._stop_frames()
            port = self._port
        if port is not None:
            self._write(port, data)

    def close(self) -> None:
        self.stop_all()
        self._stop.set()
        self._thread.join(2.0)
        with self._lock:
            port, self._port = self._port, None
        if port is not None:
            try:
                port.flush()
            except Exception:  # noqa: BLE001 - closing a dead port
                pass
            port.close()

    # -- internals ------------------------------------------------------------------------
    def _write(self, port: Any, data: bytes) -> bool:
        """Write ``data``; whether it went out (a timed-out write may have: pyserial cannot say,
        so it counts as not written)."""
        try:
            port.write(data)
        except serial.SerialTimeoutException as exc:
            with self._lock:
                self._stalled_writes += 1
                stalled = self._stalled_writes
            if stalled >= STALLED_WRITES_LOST:
                self._lost(port, f"write failed: {exc} {stalled} times in a row")
            return False
        except (serial.SerialException, OSError) as exc:
            self._lost(port, f"write failed: {exc}")
            return False
        with self._lock:
            self._stalled_writes = 0
        return True

    def _lost(self, port: Any, reason: str) -> None:
        with self._lock:
            if self._port is port and port is not None:
                self._port = None
                self.reason = reason
                try:
                    port.close()
                except Exception:  # noqa: BLE001
                    pass

    def _expire(self, now: float) -> None:
        for key, t_sent in list(self._pending.items()):
            if now - t_sent > REPLY_TIMEOUT_S:
                del self._pending[key]
                if key[2] in MOTION:
                    s = self._by_addr[key[0]]
                    s.lost += 1
                    s.recent.append(False)
                # every request given up on is remembered: a reply to it now is late, not a stranger's
                self._expired[key] = None
                while len(self._expired) > EXPIRED_KEPT:
                    self._expired.popitem(last=False)

    def _read_loop(self) -> None:
        backoff = BACKOFF_S[0]
        while not self._stop.is_set():
            with self._lock:
                port = self._port
            if port is None:
                try:
                    port = self._opener()
                except Exception as exc:  # noqa: BLE001 - a missing device raises SerialException / OSError
                    why = HELD_ELSEWHERE if getattr(exc, "errno", None) in (errno.EAGAIN, errno.EWOULDBLOCK) else _short(exc)
                    with self._lock:
                        self.reason = f"cannot open {self.port_name}: {why}; retrying in {backoff:.2g} s"
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, BACKOFF_S[1])
                    continue
                with self._lock:
                    self._port = port
                    self._opened_at = self._clock()
                    self.parser = p.FrameParser()
                    self.connects += 1
                    self._stalled_writes = 0
                    self._stop_first = True
                    self.reason = "no reply yet"
                backoff = BACKOFF_S[0]
            try:
                data = port.read(max(1, port.in_waiting))
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                self._lost(port, f"read failed: {_short(exc)}")
                continue
            if data:
                self._take(bytes(data))
            elif self.connected is False and self._port is port:
                with self._lock:
                    if self._port is port:
                        self.reason = f"no reply for more than {SILENT_S:g} s"

    def _take(self, data: bytes) -> None:
        now = self._clock()
        with self._lock:
            frames = self.parser.feed(data)
            for _, address in self.parser.last_rejects:
                if address in self._by_addr:
                    self._by_addr[address].crc_errors += 1
            for f in frames:
                s = self._by_addr.get(f.address)
                if s is None:
                    continue
                reply = self._auth.open(f, s)
                if reply is None:
                    continue
                f, match, sealed = reply
                asked = [(f.address, match, t) for t, rs in REPLIES.items() if f.msg_type in rs]
                request = next((key for key in asked if key in self._pending), None)
                if request is None:
                    maybe = next((key for key in asked if key in self._unsent), None)
                    if maybe is not None:  # the answer to a write we counted as failed: not sent, not a stranger
                        if now - self._unsent.pop(maybe) <= REPLY_TIMEOUT_S:
                            s.prev_reply, s.last_reply = s.last_reply, now
                        continue
                    late = next((key for key in asked if key in self._expired), None)
                    if late is None:
                        s.unmatched += 1
                        continue
                    del self._expired[late]
                    if late[2] in MOTION:  # counted lost when given up on: it was late
                        s.lost -= 1
                        s.late += 1
                    continue  # it is there, but what it says is old news: not an answer, not alive
                t_sent = self._pending.pop(request)
                if now - t_sent > REPLY_TIMEOUT_S:  # matched, but after the timeout (not yet expired): late
                    if request[2] in MOTION:
                        s.late += 1
                        s.recent.append(False)
                    continue
                if sealed:
                    s.authenticated += 1
                    s.legacy = False
                elif s.legacy and not self.allow_unauthenticated:
                    continue  # an older robot answers, but it is not driven: not alive for the loop
                s.prev_reply, s.last_reply = s.last_reply, now
                if request[2] in MOTION:
                    s.answered += 1
                    s.recent.append(True)
                    rtt = (now - t_sent) * 1e3
                    s.rtt_ms = rtt
                    s.rtt_mean_ms = rtt if math.isnan(s.rtt_mean_ms) else 0.9 * s.rtt_mean_ms + 0.1 * rtt
                if f.msg_type in (p.MSG_ACK, p.MSG_DRIVEN):
                    a = p.decode_ack(f) if f.msg_type == p.MSG_ACK else p.decode_driven(f)[0]
                    s.v_meas, s.w_meas, s.flags = a.v_mps, a.w_rps, a.flags
                    s.left_ticks, s.right_ticks = a.left_ticks, a.right_ticks
                elif f.msg_type == p.MSG_STATUS:
                    if not sealed:  # a plain STATUS to our plain PING: protocol 1 or 2
                        s.legacy = s.authenticated == 0
                        st = p.decode_status(f)
                    else:
                        st, s.refusals = p.decode_status_counts(f)
                    s.battery_mv, s.flags = st.battery_mv, st.flags
                else:  # OWNER or NACK: who holds the robot, as it says
                    o = p.decode_ownership(f)
                    s.owner = o.owner
                    if f.msg_type == p.MSG_OWNER:
                        if not s.owned and self.on_owned is not None:
                            self.on_owned(f.address)
                        s.owned = True
                    elif o.reason == p.NACK_STALE:
                        s.stale += 1  # still ours; it stands still until a fresh command
                    else:  # another's, or no longer ours (its lease lapsed and another took it): at once
                        s.owned = False
                        # our own lapsed lease (our DRIVEs lost for its length): ask again at once
                        s.next_claim = now if o.owner == self.radio_id else now + CLAIM_RETRY_S
                        s.v_meas = s.w_meas = 0.0


def _age_ms(observed_at: float, now: float, v: float, w: float) -> int:
    """The age DRIVE carries: of the observation the command came from; a command to stand still
    is safe whatever one saw (0); a moving one from an unknown observation is refused (65535)."""
    if v == 0.0 and w == 0.0:
        return 0
    if not math.isfinite(observed_at):
        return 0xFFFF
    return int(min(0xFFFF, max(0.0, (now - observed_at) * 1000.0)))


def _alive(s: FollowerLinkStats, now: float, within: float) -> bool:
    """The robot answered in time within ``within`` of now, and the answer before came within the
    reply timeout of it: two in a row, so one chance match of a repeated sequence number is not life."""
    return now - s.last_reply < within and s.last_reply - s.prev_reply < REPLY_TIMEOUT_S


def _name(address: int) -> str:
    return f"F{address}" if address != p.LEADER_ADDRESS else "leader base"


HELD_ELSEWHERE = "another link holds it, in this program or another (one link drives a port's robots)"


def open_port(port: str, baud: int) -> Any:
    """``port`` for this link alone (pyserial's ``exclusive``: an flock, gone with the port's close or
    the process): another link's open (a second service on the dongle, a retried path that names a
    reused pseudo-terminal now) is refused (HELD_ELSEWHERE), so no robot hears two programs."""
    return serial.serial_for_url(port, baudrate=baud, timeout=0.02, write_timeout=0.05, exclusive=True)


def _short(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0][:120]


class PortPerFollowerLink:
    """One serial port per follower: follower i on ``ports[i]``, at address i + 1. The same
    FollowerLink as :class:`SerialLink`; each port has its own reader, back-off and stats."""

    def __init__(self, ports: list[str], baud: int = 115200, v_max: float = 0.3, w_max: float = 2.0,
                 **auth: Any) -> None:
        """``auth``: SerialLink's radio_key, sender_id, allow_unauthenticated and counter (shared)."""
        self.port_name = ",".join(ports)
        self.links = [SerialLink(port, 1, baud, v_max, w_max, addresses=[i + 1], **auth)
                      for i, port in enumerate(ports)]

    @property
    def n(self) -> int:
        return len(self.links)

    @property
    def connects(self) -> int:
        return min(link.connects for link in self.links)

    @property
    def lost(self) -> bool:
        """No follower on any port answers."""
        return all(link.lost for link in self.links)

    @property
    def link_state(self) -> str:
        bad = [f"F{i + 1} {link.link_state}" for i, link in enumerate(self.links) if not link.link_state.endswith(": ok")]
        return f"serial {self.n} ports: ok" if not bad else "; ".join(bad)

    def detail(self) -> str:
        return "; ".join(link.detail() for link in self.links)

    def answering(self) -> np.ndarray:
        return np.concatenate([link.answering() for link in self.links])

    def measured(self) -> tuple[FloatArray, FloatArray]:
        parts = [link.measured() for link in self.links]
        return np.concatenate([v for v, _ in parts]), np.concatenate([w for _, w in parts])

    def send(self, commands: Commands) -> None:
        v, w = np.asarray(commands.v, dtype=float), np.asarray(commands.w, dtype=float)
        for i, link in enumerate(self.links):
            link.send(Commands(v[i:i + 1] if i < len(v) else np.zeros(1), w[i:i + 1] if i < len(w) else np.zeros(1)))

    def close(self) -> None:
        for link in self.links:
            link.close()


def link_ports(port_spec: str) -> list[str]:
    """The ports of ``--link serial:PORT[,PORT...]``; ValueError (one line) for an empty name."""
    ports = [p_.strip() for p_ in port_spec.split(",")]
    if any(not p_ for p_ in ports):
        raise ValueError(f"--link serial:{port_spec}: an empty port name in the list")
    return ports


def same_device(a: str, b: str) -> bool:
    """Whether two port names name one device (through a symlink, ``..``)."""
    return os.path.realpath(a) == os.path.realpath(b)


def make_link(port_spec: str, n: int, baud: int = 115200, v_max: float = 0.3,
              w_max: float = 2.0, radio_id: int | None = None, radio_key: bytes | None = None,
              sender_id: int | None = None, allow_unauthenticated: bool = False,
              counter: FrameCounter | None = None) -> SerialLink | PortPerFollowerLink:
    """One port for the whole team, or a comma-separated list: one port per follower.
    ``radio_id``: this leader's number on a shared radio (protocol 2; one port only).

    ValueError (one line) when the number of ports is neither 1 nor n, or a port is named twice."""
    ports = link_ports(port_spec)
    for k, port in enumerate(ports):
        if any(same_device(port, earlier) for earlier in ports[:k]):
            raise ValueError(f"--link serial:{port_spec}: {port} is named twice (one device): one port per follower")
    if radio_id is not None and len(ports) != 1:
        raise ValueError("--radio-id: a radio is one port that every leader shares; give one (serial:PATH)")
    if len(ports) == 1:
        return SerialLink(ports[0], n, baud, v_max, w_max, radio_id=radio_id, radio_key=radio_key,
                          sender_id=sender_id, allow_unauthenticated=allow_unauthenticated, counter=counter)
    if len(ports) != n:
        raise ValueError(f"--link serial:{port_spec}: {len(ports)} ports for {n} followers; give one port for the"
                         " whole team or one per follower")
    counter = counter or FrameCounter()  # one sender, one counter across its ports
    return PortPerFollowerLink(ports, baud, v_max, w_max, radio_key=radio_key, sender_id=sender_id,
                               allow_unauthenticated=allow_unauthenticated, counter=counter)
