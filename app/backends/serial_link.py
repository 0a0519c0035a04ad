"""The follower link over a serial port (cable, USB-serial, or a radio dongle): pyserial.

One port serves every follower (addressed frames, as on a shared radio); give one
``SerialLink`` per port for one port per follower. ``send`` is called by the loop once
per tick: it writes one SET_VELOCITY per follower (zero when stopped, which also feeds
their watchdogs) and returns at once; a reader thread parses the replies and keeps, per
follower, the round-trip time, lost replies, CRC errors, the encoder odometry and the
status (battery, watchdog). When the port fails or goes silent the link says "link lost"
and reopens the port with back-off (0.25 s doubling to 2 s) without ever blocking the loop.

Every command is clamped again here to the limits given (defence in depth: the controller
already clamps), NaN becomes 0, and ``close`` sends STOP to every follower.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import serial

from core.link import protocol as p
from core.types import Commands, FloatArray

REPLY_TIMEOUT_S = 0.25  # a SET_VELOCITY not answered by then counts as a lost reply
SILENT_S = 0.5  # no reply at all for this long: "link lost"
# pyserial raises its write timeout whenever a write call took longer than the timeout, even
# when every byte went out (a thread held off the CPU for 50 ms): one timed-out write is not
# a dead port. This many in a row is (the port takes no bytes): closed and reopened.
STALLED_WRITES_LOST = 3
ODOMETRY_STALE_S = 0.2  # measured velocities older than this are taken as zero
PING_PERIOD_S = 1.0  # each follower's STATUS (battery, watchdog) is asked for this often
BACKOFF_S = (0.25, 2.0)


@dataclass
class FollowerLinkStats:
    address: int
    sent: int = 0
    acks: int = 0
    lost: int = 0
    crc_errors: int = 0  # refused frames (bad CRC, length, type) whose address byte named this follower
    rtt_ms: float = math.nan  # last round trip
    rtt_mean_ms: float = math.nan  # running mean
    last_reply: float = -math.inf  # monotonic time
    v_meas: float = 0.0
    w_meas: float = 0.0
    left_ticks: int = 0
    right_ticks: int = 0
    flags: int = 0
    battery_mv: int = 0


def parse_link_spec(spec: str) -> str:
    """``serial:PATH`` (or a pyserial URL such as ``serial:socket://host:port``) -> the port's name.

    ValueError with one line for anything else."""
    kind, _, rest = spec.partition(":")
    if kind == "sim" and not rest:
        return ""
    if kind != "serial" or not rest:
        raise ValueError(f"--link {spec!r}: must be 'sim' or 'serial:PATH' (e.g. serial:/dev/ttyUSB0)")
    return rest


class SerialLink:
    """A FollowerLink to ``n`` followers at addresses 1..n on one serial port (or to the
    leader base at address 0: the LeaderOdometry port, see app.backends.hardware)."""

    def __init__(self, port: str, n: int, baud: int = 115200, v_max: float = 0.3, w_max: float = 2.0,
                 clock: Callable[[], float] = time.monotonic,
                 opener: Callable[..., Any] | None = None, addresses: list[int] | None = None) -> None:
        """``addresses``: instead of 1..n, e.g. [0] for the leader base (docs/follower-protocol.md)."""
        self.port_name = port
        self.baud = baud
        self.v_max, self.w_max = v_max, w_max
        self.addresses = list(addresses) if addresses is not None else list(range(1, n + 1))
        self.stats = [FollowerLinkStats(a) for a in self.addresses]
        self._by_addr = {s.address: s for s in self.stats}
        self.parser = p.FrameParser()
        self._clock = clock
        self._opener = opener or (lambda: serial.serial_for_url(port, baudrate=baud, timeout=0.02, write_timeout=0.05))
        self._port: Any = None
        self._lock = threading.Lock()  # guards _port, _pending, stats
        self._pending: dict[tuple[int, int], float] = {}
        self._seq = 0
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
        now = self._clock()
        with self._lock:
            if self._port is None:
                return False
            last = max((s.last_reply for s in self.stats), default=-math.inf)
        return now - max(last, self._opened_at) < SILENT_S

    @property
    def link_state(self) -> str:
        if self.connected:
            return f"serial {self.port_name}: ok"
        return f"link lost ({self.reason})"

    def detail(self) -> str:
        """Per follower: round trip, lost replies, CRC errors, battery, watchdog."""
        now = self._clock()
        parts = []
        with self._lock:
            for s in self.stats:
                age = now - s.last_reply
                flags = ("watchdog " if s.flags & p.FLAG_WATCHDOG else "") + ("stopped " if s.flags & p.FLAG_STOPPED else "")
                name = f"F{s.address}" if s.address != p.LEADER_ADDRESS else "leader base"
                parts.append(f"{name} rtt {s.rtt_mean_ms:.1f} ms, lost {s.lost}/{s.sent}, crc {s.crc_errors}, "
                             f"{s.battery_mv / 1000:.2f} V" + (f", {flags.strip()}" if flags else "")
                             + (f", silent {age:.1f} s" if age > SILENT_S and math.isfinite(age) else ""))
        return "; ".join(parts)

    def measured(self) -> tuple[FloatArray, FloatArray]:
        """(v, w) per follower from the encoders; zero where the odometry is stale."""
        now = self._clock()
        with self._lock:
            fresh = np.array([now - s.last_reply < ODOMETRY_STALE_S for s in self.stats])
            v = np.array([s.v_meas for s in self.stats])
            w = np.array([s.w_meas for s in self.stats])
        return np.where(fresh, v, 0.0), np.where(fresh, w, 0.0)

    # -- FollowerLink ---------------------------------------------------------------------
    def send(self, commands: Commands) -> None:
        """One SET_VELOCITY per follower (clamped), written without blocking the loop."""
        v = np.clip(np.nan_to_num(np.asarray(commands.v, dtype=float)), -self.v_max, self.v_max)
        w = np.clip(np.nan_to_num(np.asarray(commands.w, dtype=float)), -self.w_max, self.w_max)
        now = self._clock()
        with self._lock:
            self._seq = (self._seq + 1) & 0xFF
            seq = self._seq
            out = bytearray()
            for i, s in enumerate(self.stats):
                vi = float(v[i]) if i < len(v) else 0.0
                wi = float(w[i]) if i < len(w) else 0.0
                out += p.encode_frame(p.set_velocity(s.address, seq, vi, wi))
                s.sent += 1
                self._pending[(s.address, seq)] = now
            if now >= self._next_ping and self.stats:
                s = self.stats[self._ping_index % len(self.stats)]
                self._ping_index += 1
                out += p.encode_frame(p.ping(s.address, seq))
                self._next_ping = now + PING_PERIOD_S / len(self.stats)
            self._expire(now)
            port = self._port
        if port is not None:
            self._write(port, bytes(out))

    def stop_all(self) -> None:
        """STOP to every follower, addressed (answered) and broadcast (for robots we do not know)."""
        with self._lock:
            self._seq = (self._seq + 1) & 0xFF
            data = b"".join(p.encode_frame(p.stop(a, self._seq)) for a in self.addresses)
            data += p.encode_frame(p.stop(p.BROADCAST, self._seq))
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
    def _write(self, port: Any, data: bytes) -> None:
        try:
            port.write(data)
        except serial.SerialTimeoutException as exc:
            with self._lock:
                self._stalled_writes += 1
                stalled = self._stalled_writes
            if stalled >= STALLED_WRITES_LOST:
                self._lost(port, f"write failed: {exc} {stalled} times in a row")
            return
        except (serial.SerialException, OSError) as exc:
            self._lost(port, f"write failed: {exc}")
            return
        with self._lock:
            self._stalled_writes = 0

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
                self._by_addr[key[0]].lost += 1

    def _read_loop(self) -> None:
        backoff = BACKOFF_S[0]
        while not self._stop.is_set():
            with self._lock:
                port = self._port
            if port is None:
                try:
                    port = self._opener()
                except Exception as exc:  # noqa: BLE001 - a missing device raises SerialException / OSError
                    with self._lock:
                        self.reason = f"cannot open {self.port_name}: {_short(exc)}; retrying in {backoff:.2g} s"
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, BACKOFF_S[1])
                    continue
                with self._lock:
                    self._port = port
                    self._opened_at = self._clock()
                    self.parser = p.FrameParser()
                    self.connects += 1
                    self._stalled_writes = 0
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
                s.last_reply = now
                if f.msg_type == p.MSG_ACK:
                    a = p.decode_ack(f)
                    s.acks += 1
                    s.v_meas, s.w_meas, s.flags = a.v_mps, a.w_rps, a.flags
                    s.left_ticks, s.right_ticks = a.left_ticks, a.right_ticks
                    t_sent = self._pending.pop((f.address, f.seq), None)
                    if t_sent is not None:
                        rtt = (now - t_sent) * 1e3
                        s.rtt_ms = rtt
                        s.rtt_mean_ms = rtt if math.isnan(s.rtt_mean_ms) else 0.9 * s.rtt_mean_ms + 0.1 * rtt
                elif f.msg_type == p.MSG_STATUS:
                    st = p.decode_status(f)
                    s.battery_mv, s.flags = st.battery_mv, st.flags


def _short(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0][:120]


class PortPerFollowerLink:
    """One serial port per follower: follower i on ``ports[i]``, at address i + 1. The same
    FollowerLink as :class:`SerialLink`; each port has its own reader, back-off and stats."""

    def __init__(self, ports: list[str], baud: int = 115200, v_max: float = 0.3, w_max: float = 2.0) -> None:
        self.port_name = ",".join(ports)
        self.links = [SerialLink(port, 1, baud, v_max, w_max, addresses=[i + 1]) for i, port in enumerate(ports)]

    @property
    def n(self) -> int:
        return len(self.links)

    @property
    def connects(self) -> int:
        return min(link.connects for link in self.links)

    @property
    def link_state(self) -> str:
        lost = [f"F{i + 1} {link.link_state}" for i, link in enumerate(self.links) if not link.connected]
        return f"serial {self.n} ports: ok" if not lost else "; ".join(lost)

    def detail(self) -> str:
        return "; ".join(link.detail() for link in self.links)

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


def make_link(port_spec: str, n: int, baud: int = 115200, v_max: float = 0.3,
              w_max: float = 2.0) -> SerialLink | PortPerFollowerLink:
    """One port for the whole team, or a comma-separated list: one port per follower.

    ValueError (one line) when the number of ports is neither 1 nor n."""
    ports = [p_.strip() for p_ in port_spec.split(",")]
    if any(not p_ for p_ in ports):
        raise ValueError(f"--link serial:{port_spec}: an empty port name in the list")
    if len(ports) == 1:
        return SerialLink(ports[0], n, baud, v_max, w_max)
    if len(ports) != n:
        raise ValueError(f"--link serial:{port_spec}: {len(ports)} ports for {n} followers; give one port for the"
                         " whole team or one per follower")
    return PortPerFollowerLink(ports, baud, v_max, w_max)
