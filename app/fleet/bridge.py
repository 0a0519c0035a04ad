"""A leader on the fleet bus: its team's state, its events and its liveliness over Eclipse
Zenoh, and the parameter changes addressed to it (paper §6: leaders that see each other and
can take over each other's robots build on this). The key expressions and payloads are in
docs/fleet-protocol.md; a plain Zenoh subscriber (or a ROS 2 system on rmw_zenoh) reads them.

Every process is a Zenoh router with multicast and gossip scouting off: it listens on and
connects to the endpoints it is given, and nothing else finds it (:func:`zenoh_config`).
Without the fleet's keys every endpoint is on loopback; with them (``--keys``,
app.fleet.security) every link is mutual TLS and Zenoh's access control lets each identity
write only its own keys.

Who may command the robots over the bus: a fleet-wide STOP is always obeyed (stopping is
always safe); anything else (gains, formation, leader motion, releasing STOP) only when the
operator started the leader with ``--fleet-control``; otherwise it is refused and the refusal
published as an event. A command is checked as the page's values are (app.params): bad
values are refused or clamped with the notice published.

The state is published from a thread of its own with the newest tick only (the robots' loop
never waits on the network), the events from the parameter store's listeners.
"""

from __future__ import annotations

import json
import logging
import math
import re
import secrets
import threading
import time
from dataclasses import dataclass
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from app import wire

from app.keys import robot_index, robot_name, root
from app.params import Params, ParamsStore, params_events
from app.refusals import Refusals
from core.bounds import BUS, settable_by
from core.types import Gains
from app.tick import SessionClock, TickState

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    import zenoh

    from app.fleet.security import FleetKeys

NAME = re.compile(r"[A-Za-z0-9_-]{1,32}")
ENDPOINT = re.compile(r"(tcp|udp|tls)/(?P<host>[A-Za-z0-9_.-]+|\[[0-9a-fA-F:]+\]):(?P<port>\d{1,5})")
SETTABLE = settable_by(BUS)  # the parameter table's rows the bus may set (core.bounds)


def check_name(value: str, what: str) -> str:
    """A fleet or leader name that is one key-expression chunk, else ValueError (one line)."""
    if not NAME.fullmatch(value):
        raise ValueError(f"{what} {value!r}: 1 to 32 characters of A-Z, a-z, 0-9, _ and - (it names keys on the bus)")
    return value


def check_endpoint(value: str, keys: FleetKeys | None = None) -> str:
    """An endpoint this process may use, as it is to be used: with fleet keys ``tls/HOST:PORT``
    (mutual TLS), without them a ``tcp/`` or ``udp/`` one whose host is loopback by every
    address it resolves to, returned with the address checked in place of the name (an open
    bus is for one machine); else ValueError (one line)."""
    m = ENDPOINT.fullmatch(value)
    if m is None or not 0 < int(m["port"]) < 65536:
        raise ValueError(f"endpoint {value!r}: must be tls/HOST:PORT with --keys, or tcp/HOST:PORT or udp/HOST:PORT"
                         " on loopback without (e.g. tcp/127.0.0.1:7447)")
    if keys is not None and not value.startswith("tls/"):
        raise ValueError(f"endpoint {value!r}: with --keys every endpoint is tls/HOST:PORT (mutual TLS; a plain"
                         " one would let anyone in)")
    if keys is None:
        if value.startswith("tls/"):
            raise ValueError(f"endpoint {value!r}: tls/ needs the fleet's keys (--keys DIR, made by"
                             " `omniformation fleet-keys`)")
        address = _loopback_address(value, m["host"], int(m["port"]))
        return f"{value[:3]}/{address}:{m['port']}"
    return value


def _loopback_address(value: str, host: str, port: int) -> str:
    """The address an open endpoint's host names, if every address it resolves to is loopback
    (a name is judged by what it names: ``127.lan`` may be 192.0.2.2), as Zenoh writes it;
    else ValueError (one line naming the address)."""
    import ipaddress
    import socket

    open_bus = ("without --keys the bus stays on this machine (127.0.0.1, localhost, [::1]); anyone on a network"
                " could drive the robots: make keys with `omniformation fleet-keys` and use tls/ endpoints with"
                " --keys")
    name = host[1:-1] if host.startswith("[") else host
    try:
        found = [ipaddress.ip_address(name)]
    except ValueError:
        try:
            infos = socket.getaddrinfo(name, port, type=socket.SOCK_STREAM)
        except (OSError, UnicodeError) as exc:
            raise ValueError(f"endpoint {value!r}: {name!r} does not resolve ({exc}); {open_bus}") from None
        found = [ipaddress.ip_address(str(info[4][0]).split("%")[0]) for info in infos]
    for address in found:
        if not address.is_loopback:
            raise ValueError(f"endpoint {value!r}: {name} is {address}, not loopback; {open_bus}")
    if not found:
        raise ValueError(f"endpoint {value!r}: {name!r} resolves to no address; {open_bus}")
    first = next((a for a in found if a.version == 4), found[0])  # 127.0.0.1 where a name is both
    return f"[{first}]" if first.version == 6 else str(first)


def loopback_endpoint() -> str:
    """A TCP endpoint on a loopback port free at the time of asking: a bus of its own for a bench
    or a test (the port is let go before Zenoh listens on it)."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{sock.getsockname()[1]}"


def zenoh_config(listen: list[str], connect: list[str], keys: FleetKeys | None = None) -> Any:
    """Only what is named: every omniformation process is a Zenoh router (routers forward for
    one another, so a leader connected to a hub hears the leaders connected to it); one that
    is not told to listen has no listener at all; multicast and gossip scouting are off, so
    nothing finds anything by itself (docs/fleet-protocol.md, "Joining"). Zenoh peers would
    not do: without gossip they do not forward between other peers, and with it they connect
    to whomever they hear of."""
    import zenoh

    from app.fleet.security import session_config

    config: dict[str, Any] = {
        "mode": "router",
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "listen": {"endpoints": list(listen)}, "connect": {"endpoints": list(connect)},
    }
    if keys is not None:
        config.update(session_config(keys))
    return zenoh.Config.from_json5(json.dumps(config))


def open_session(listen: list[str], connect: list[str], keys: FleetKeys | None = None) -> zenoh.Session:
    """A Zenoh session on these endpoints (checked first: ValueError names a bad one). With
    ``keys``: mutual TLS and the fleet's access control (app.fleet.security); only a hub
    (the arena, the page) listens."""
    import zenoh

    listen = [check_endpoint(e, keys) for e in listen]
    connect = [check_endpoint(e, keys) for e in connect]
    if keys is not None and listen and not keys.is_hub:
        raise ValueError(f"--zenoh-listen: with --keys only the fleet's hubs (the arena, the page) listen; leader"
                         f" {keys.identity} connects to one of them")
    return zenoh.open(zenoh_config(listen, connect, keys))


def name_taken(session: Any, fleet: str, leader_id: str, within_s: float = 2.0) -> bool:
    """Whether a leader with this id is alive on the fleet's bus already (its liveliness token).

    A session answers from the tokens it has heard of, at once; a session opened a moment ago
    may not have heard of them yet (on a loaded machine that took seconds here), so it asks
    again for ``within_s``. A leader that still misses its twin stands down as soon as it
    sees the other's states (FleetBridge: the one that started later gives way)."""
    deadline = time.monotonic() + within_s
    while True:
        replies = session.liveliness().get(f"{root(fleet)}/alive/{leader_id}", timeout=1.0)
        if any(getattr(r, "ok", None) is not None for r in replies):
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.1)


def _num(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return [_num(v) for v in x.tolist()]
    if isinstance(x, (list, tuple)):
        return [_num(v) for v in x]
    if isinstance(x, (float, np.floating)):
        f = float(x)
        return round(f, 5) if math.isfinite(f) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def read_state(msg: Any) -> dict[str, Any]:
    """A leader's state as docs/fleet-protocol.md gives it, each field a reader uses of its exact
    type (app.wire: a state may carry more), else BadMessage."""
    state = wire.obj(msg, "a state", ("p_est",), more=True)

    def maybe(x: Any, what: str) -> None:
        if x is not None:
            wire.number(x, what)

    for name in ("p_est", "p_d", "p_true", "commands"):
        rows = state.get(name) or []  # p_true: null where nobody knows it
        if not isinstance(rows, list) or not all(isinstance(r, list) and len(r) == 2 for r in rows):
            raise wire.BadMessage(f"{name} must be a list of pairs")
        for r in rows:
            for v in r:
                maybe(v, name)
    for name in ("a_est", "error_m"):
        values = state.get(name) or []
        if not isinstance(values, list):
            raise wire.BadMessage(f"{name} must be a list")
        for v in values:
            maybe(v, name)
    tracked = state.get("tracked", [])
    if not isinstance(tracked, list) or not all(isinstance(b, bool) for b in tracked):
        raise wire.BadMessage("tracked must be a list of true/false")
    if state.get("leader") is not None:
        wire.numbers(state["leader"], 3, "leader")
    wire.numbers(state.get("leader_twist", [0.0, 0.0]), 2, "leader_twist")
    for name in ("t", "rate_hz", "sent", "started"):
        maybe(state.get(name), name)
    for name in ("stopped",):
        if not isinstance(state.get(name, False), bool):
            raise wire.BadMessage(f"{name} must be true or false")
    for name in ("phase", "takes", "link_state", "leader_id", "instance"):
        wire.text(state.get(name, ""), name, 1000)
    robots = state.get("robots", [])
    if not isinstance(robots, list) or not all(robot_index(r, 1_000_000) is not None for r in robots):
        raise wire.BadMessage("robots must be a list of robot names (R1, R2, ...)")
    for name in ("gains", "refused"):
        table = state.get(name, {})
        if not isinstance(table, dict):
            raise wire.BadMessage(f"{name} must be an object")
        for k, v in table.items():
            wire.number(v, f"{name}.{k}")
    return state


def takes(allow_control: bool) -> str:
    """What a leader obeys from the bus, as its state says: everything (``--fleet-control``) or STOP."""
    return "all" if allow_control else "stop"


def on_the_wire(payload: dict[str, Any], presence: Presence) -> str:
    """A state as it goes on the bus: compact JSON, then which process sent it and when it
    started, and its wall clock as the last thing before it goes (a subscriber's latency on
    the same machine)."""
    text = json.dumps(payload, separators=(",", ":"))
    return (f'{text[:-1]},"instance":"{presence.instance}","started":{presence.started:.6f},'
            f'"sent":{time.time():.6f}}}')


def state_payload(s: TickState, leader_id: str, takes: str = "stop", t: float | None = None) -> dict[str, Any]:
    """What a leader publishes each tick (docs/fleet-protocol.md): compact, SI units. ``takes``:
    what it obeys from the bus ("stop", or "all" with --fleet-control); ``t``: the time said (default
    the state's)."""
    return {
        "leader_id": leader_id, "tick": s.tick, "t": _num(s.t if t is None else t), "leader": _num(s.leader),
        "leader_twist": _num(list(s.leader_twist)), "p_est": _num(s.p_est), "a_est": _num(s.a_est),
        "tracked": _num(s.tracked.astype(bool)), "p_d": _num(s.p_d), "error_m": _num(np.linalg.norm(s.p_d - s.p_est, axis=1)),
        "p_true": _num(s.p_true),
        "commands": _num(s.commands), "gains": s.gains.as_dict(), "stopped": bool(s.stopped), "phase": s.phase,
        "link_state": s.link_state, "rate_hz": _num(s.rate_hz), "takes": takes,
        **({"robots": [robot_name(r) for r in s.robots]} if s.robots is not None and len(s.robots) == s.n else {}),
    }


def waiting_payload(leader_id: str, t: float, takes: str, tick: int = 0,
                    refused: dict[str, int] | None = None) -> dict[str, Any]:
    """The state of a leader that owns no robot (it came back after its robots were adopted, or
    they were all adopted while its link was cut): an empty team, standing."""
    return {"leader_id": leader_id, "tick": tick, "t": round(t, 5), "leader": None,
            "leader_twist": [0.0, 0.0], "p_est": [], "a_est": [], "tracked": [], "p_d": [], "error_m": [],
            "p_true": [], "commands": [], "gains": Gains().as_dict(), "stopped": True, "phase": "waiting",
            "link_state": "waiting for a robot (the operator hands one over)", "rate_hz": None,
            "takes": takes, "refused": refused or {"commands": 0, "states": 0, "truths": 0}}


@dataclass(frozen=True)
class Presence:
    """This leader process among leaders that might share its id: ``instance`` (8 hex digits,
    new at every start) and ``started`` (its wall clock when it joined, Unix s): both twins
    compare the same two numbers (docs/fleet-protocol.md, "One leader per id")."""

    instance: str
    started: float

    @classmethod
    def new(cls) -> Presence:
        return cls(secrets.token_hex(4), time.time())


class WaitingState:
    """The state of a leader that owns no robot yet (it came back after its robots were
    adopted): an empty team, published every tick like any leader's state until it has robots
    (docs/fleet-protocol.md: state comes every tick), from a thread of its own."""

    def __init__(self, session: Any, fleet: str, leader_id: str, presence: Presence, allow_control: bool,
                 rate_hz: float = 30.0) -> None:
        self.leader_id = leader_id
        self.presence = presence
        self.takes = takes(allow_control)
        self.t = 0.0  # this process's session time (s), which the loop's states go on from
        self._dt = 1.0 / rate_hz
        self._pub = session.declare_publisher(f"{root(fleet)}/leader/{leader_id}/state", express=True)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="omniformation-waiting", daemon=True)
        self._thread.start()

    def payload(self) -> dict[str, Any]:
        return waiting_payload(self.leader_id, self.t, self.takes)

    def _run(self) -> None:
        start = time.monotonic()
        while not self._stop.wait(self._dt):
            self.t = time.monotonic() - start
            self._pub.put(on_the_wire(self.payload(), self.presence))

    def close(self) -> float:
        """Stop publishing; the session time reached (the loop's states go on from it)."""
        self._stop.set()
        self._thread.join(5.0)
        self._pub.undeclare()
        return self.t + self._dt


class FleetBridge:
    """One leader's presence on the bus; ``on_tick`` is the loop's subscriber."""

    def __init__(self, store: ParamsStore, fleet: str, leader_id: str, listen: list[str] | None = None,
                 connect: list[str] | None = None, allow_control: bool = False, session: Any = None,
                 token: Any = None, on_twin: Callable[[], None] | None = None, presence: Presence | None = None,
                 t_start: float = 0.0) -> None:
        """``session``: one already open (then ``listen`` / ``connect`` are its business, and
        closing the bridge leaves it open). ``token``: this leader's liveliness token when it
        was declared already (a leader waiting for robots is alive before its loop runs).
        ``on_twin``: called once if another leader with this id started first (this one must
        stop its robots and end; :attr:`twin` says why). ``presence``: this process's, when it
        was on the bus already (waiting for robots); ``t_start``: the session time it reached."""
        import zenoh

        self.presence = presence or Presence.new()  # this process among leaders that share an id by mistake
        self.twin: str | None = None
        self._on_twin = on_twin
        self._twins_seen: set[str] = set()
        self.store = store
        self.fleet = check_name(fleet, "fleet")
        self.leader_id = check_name(leader_id, "leader id")
        self.allow_control = allow_control
        self.base = f"{root(fleet)}/leader/{leader_id}"
        self._own_session = session is None
        self.session = session if session is not None else open_session(listen or [], connect or [])
        self.endpoints = list(connect or []) + list(listen or [])
        self.commands_taken = 0
        self.commands_refused = 0  # every refused command, counted (the state says it); said through:
        # a flood of bad commands must not become a flood of events on the bus (app.refusals)
        self.refusals = Refusals(say=lambda line: self.event("refused", line))
        self.states_refused = 0  # messages under this leader's own state key that are no leader's state
        self._state_pub = self.session.declare_publisher(f"{self.base}/state", express=True,  # not batched: latency
                                                         congestion_control=zenoh.CongestionControl.DROP)
        self._event_pub = self.session.declare_publisher(f"{self.base}/events")
        self._token = token if token is not None else \
            self.session.liveliness().declare_token(f"{root(fleet)}/alive/{leader_id}")
        self._subs = [self.session.declare_subscriber(f"{self.base}/cmd", self._on_command),
                      self.session.declare_subscriber(f"{root(fleet)}/all/cmd", self._on_fleet_command),
                      # a twin's states only: its own (30 a second) would be read and dropped
                      self.session.declare_subscriber(f"{self.base}/state", self._on_own_id_state,
                                                      allowed_origin=zenoh.Locality.REMOTE)]
        self._last_params = store.get()
        self._t = 0.0
        self._clock = SessionClock(t_start)
        store.subscribe(self._on_params)
        self._closed = False
        self.empty: Callable[[], bool] = lambda: False  # set by an arena leader: it owns no robot now
        self.truths_refused: Callable[[], int] = lambda: 0  # set by an arena leader: truths it did not take

    @property
    def instance(self) -> str:
        return self.presence.instance

    @property
    def started(self) -> float:
        """Its wall clock when it joined: both twins compare the same two numbers."""
        return self.presence.started

    def peers(self) -> int:
        """How many Zenoh peers this leader's session is connected to now."""
        return len(list(self.session.info.peers_zid()))

    def status(self) -> str:
        """The bus for people: connected, or disconnected (Zenoh keeps retrying; the loop runs)."""
        n = self.peers()
        if n:
            return f"fleet {self.fleet}/{self.leader_id}: connected ({n} peer{'s' if n > 1 else ''})"
        where = f" at {', '.join(self.endpoints)}" if self.endpoints else ""
        return f"fleet {self.fleet}/{self.leader_id}: disconnected (no peer{where}; retrying)"

    # -- out ------------------------------------------------------------------------------
    def on_tick(self, s: TickState) -> None:
        """Every tick of the loop, on its thread once the tick's commands are on their way: the state
        goes on the bus at once. Encoding it (about 0.1 ms) costs less than handing it to a thread of
        its own did: that thread's wake-up and the interpreter lock passed to it and back took 4 % of a
        vision leader's CPU. A put never waits (congestion control DROP, as the loop's drive messages
        to an arena). The state's ``t`` on the bus is this process's session time, which never goes
        back (the loop's own restarts at 0 when the team changes)."""
        self._t = self._clock(s.t)
        if not self._closed:
            self._publish_state(s, self._t)

    def _publish_state(self, s: TickState, t: float) -> None:
        """``s`` said at session time ``t`` (the state itself is every subscriber's: not copied)."""
        refused = {"commands": self.commands_refused, "states": self.states_refused, "truths": self.truths_refused()}
        if self.empty():  # every robot it had is another's now: its loop holds none of them
            payload = waiting_payload(self.leader_id, t, takes(self.allow_control), s.tick, refused)
        else:
            payload = state_payload(s, self.leader_id, takes(self.allow_control), t)
            payload["refused"] = refused
        self._state_pub.put(on_the_wire(payload, self.presence))

    def event(self, kind: str, detail: str) -> None:
        self._event_pub.put(json.dumps({"leader_id": self.leader_id, "t": round(self._t, 3), "kind": kind,
                                        "detail": detail}))

    def _on_params(self, p: Params, source: str, notices: tuple[Any, ...]) -> None:
        old, self._last_params = self._last_params, p
        for kind, detail in params_events(old, p, source):
            self.event(kind, f"{detail} ({source})")
        if old.stop != p.stop:
            self.event("stop", f"{'STOP: every follower at zero' if p.stop else 'STOP released'} ({source})")
        for n in notices:
            self.event("notice", n.message)

    # -- in -------------------------------------------------------------------------------
    def _on_own_id_state(self, sample: Any) -> None:
        """States under this leader's own id: its own, or a twin's (docs/fleet-protocol.md,
        "One leader per id"). Of two twins the one that started later stands down; both
        compare the same (started, instance) pairs, so exactly one of them does."""
        try:
            msg = wire.decode(sample.payload.to_bytes())
        except wire.BadMessage:
            msg = None
        other, started = (msg.get("instance"), msg.get("started")) if isinstance(msg, dict) else (None, None)
        if other == self.instance:
            return
        # a twin is a leader: it says which process it is and when it started. Anything else under
        # this id (a forged or damaged message) is no reason to stop the robots: counted, told
        if not (isinstance(other, str) and re.fullmatch(r"[0-9a-f]{8}", other) and isinstance(started, (int, float))
                and not isinstance(started, bool) and math.isfinite(started)):
            self.states_refused += 1
            if self.states_refused in (1, 10, 100, 1000):
                self.event("refused", f"{self.states_refused} message(s) on {self.base}/state that are not a"
                                      " leader's state (no instance and start time): ignored")
            return
        other_started = float(started)
        if (other_started, other) < (self.started, self.instance):
            if self.twin is not None:
                return
            self.twin = (f"--leader-id {self.leader_id}: a leader with this id is alive on fleet {self.fleet} already"
                         f" (it started first); this one stood down and stopped its robots; every leader needs"
                         " its own id")
            log.warning("%s", self.twin)
            self.event("twin", f"a second {self.leader_id} ({self.instance}) found {other} running first and stood down")
            if self._on_twin is not None:
                self._on_twin()
        elif other not in self._twins_seen:
            self._twins_seen.add(other)
            self.event("twin", f"a second {self.leader_id} ({other}) appeared; it started later and stands down")

    def _changes(self, sample: Any) -> tuple[dict[str, Any], str]:
        """A command's changes, each value of its setting's exact type (app.wire), and who sent
        it; or no changes and why not."""
        try:
            msg = wire.obj(wire.decode(sample.payload.to_bytes()), "a command", ("set",), ("from",))
            if not isinstance(msg["set"], dict):
                raise wire.BadMessage('must be {"set": {NAME: VALUE, ...}}')
            unknown = [k for k in msg["set"] if k not in SETTABLE]
            if unknown:
                raise wire.BadMessage(f"{str(unknown[0])[:40]!r} cannot be set over the bus (allowed:"
                                      f" {', '.join(SETTABLE)})")
            changes = {k: wire.setting(k, v) for k, v in msg["set"].items()}
            sender = wire.text(msg.get("from", "?"), "from")
        except wire.BadMessage as exc:
            return {}, str(exc)
        return changes, sender[:40]

    def _apply(self, changes: dict[str, Any], sender: str) -> None:
        try:
            self.store.update_from(BUS, f"fleet:{sender}", **changes)
            self.commands_taken += 1
        except (ValueError, TypeError) as exc:
            self.commands_refused += 1
            self.refusals.refuse("bus: a value refused", sender, str(exc))

    def _on_command(self, sample: Any) -> None:
        changes, sender = self._changes(sample)
        if not changes:
            self.commands_refused += 1
            self.refusals.refuse("bus: a malformed command", _sender_of(sample), f"a command on {self.base}/cmd: {sender}")
            return
        if not self.allow_control and changes != {"stop": True}:
            self.commands_refused += 1
            self.refusals.refuse("bus: control not allowed", sender, "this leader takes only STOP over the bus (started"
                                 " without --fleet-control)")
            return
        self._apply(changes, sender)

    def _on_fleet_command(self, sample: Any) -> None:
        changes, sender = self._changes(sample)
        if changes != {"stop": True}:
            self.commands_refused += 1
            self.refusals.refuse("bus: a fleet-wide command not STOP", _sender_of(sample) if not changes else sender,
                                 f"fleet-wide commands are STOP only ({{\"set\": {{\"stop\": true}}}}), got {sender}"
                                 if not changes else f"fleet-wide commands are STOP only, got {sorted(changes)}")
            return
        self._apply(changes, sender)

    def close(self) -> None:
        self._closed = True
        for s in self._subs:
            s.undeclare()
        self._token.undeclare()
        if self._own_session:
            self.session.close()


def _sender_of(sample: Any) -> str:
    """Who a command that could not be read says it is from (its "from", if any can be read), for
    the refusal's first line per sender."""
    try:
        msg = json.loads(sample.payload.to_bytes()[:4096])
    except (ValueError, RecursionError, AttributeError):
        return "?"
    who = msg.get("from") if isinstance(msg, dict) else None
    return who[:40] if isinstance(who, str) and who else "?"
