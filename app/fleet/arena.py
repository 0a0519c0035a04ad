"""`omniformation arena FLEET`: one simulated world for every leader of a fleet (paper §6).

The arena steps every leader and every robot (core.fleet.step_arena) at the scenario's rate
and publishes the truth each step; the leaders (``run --arena FLEET --leader-id ID``) drive
their own robots through it. It is also the robots' command channel, so it decides who may
command which robot:

* a leader's drive message names the robots it commands; a robot that is not that leader's
  is not moved by it and the attempt counts as a **conflict** (never expected: 0);
* a robot whose last command is older than the followers' watchdog (0.5 s,
  docs/follower-protocol.md) stops by itself, as a real one does; a leader whose last twist
  is that old stands still too. A real robot's timer runs continuously; the arena steps, so a
  command that would pass 0.5 s of age during a step is zeroed for the whole step: a robot
  never moves on a command older than 0.5 s;
* who owns a robot is the robot's to say, as on real robots: each arena robot runs the
  followers' own rules (core.link.follower, held to the reference firmware by
  tests/app/backends/test_firmware.py), protocol 2's owner and lease included. A leader's drive for a
  robot reaches it as a DRIVE (with the age of the truth it was computed from), a claim as a
  CLAIM, the operator's handover as a HANDOVER from the robot's owner; the robot obeys, grants
  or refuses (docs/follower-protocol.md, "Ownership"). A leader's lease (1 s) lives while its
  drives come; when it went quiet (process killed, network lost) its robots are orphans, and a
  **claim** by a living leader is granted by the robot once the lease has lapsed (the first
  claim wins). The robots of a leader that has not joined yet are nobody's to take;
* with ``--radio`` the arena is only the world: every leader has a radio (a pty,
  app.backends.radio) that reaches every robot, and the robots take commands, claims and
  handovers from the radio alone. The arena's drive key then carries a leader's own twist.

Key expressions and payloads: docs/fleet-protocol.md ("The arena").
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.bounds import LEADER_SPEED, LEADER_TURN
from core.control.safety import SafetySettings
from core.fleet import MAX_TEAM, ArenaState, FleetScenario, closest_distance, initial_arena, step_arena
from core.link import protocol as p
from core.link.follower import FollowerState, RadioAuth
from core.link.protocol import WATCHDOG_S
from core.types import FloatArray

from app.backends.emulator import FollowerEmulator
from app import wire
from app.backends.radio import Radio
from app.keys import robot_index, robot_name, root

log = logging.getLogger(__name__)

STALE_DRIVE_S = 0.5  # a drive computed from a truth older than this moves nothing
CONTACT_M = SafetySettings().min_distance_m  # two bodies' centres closer than this: the safety filter's limit broken
LEASE_MS = 1000  # the lease a claim asks for on a leader's behalf (as `run --radio-id` does)
START_LEASE_MS = LEASE_MS  # at power-up each robot is its scenario leader's, as if just claimed


@dataclass
class ArenaCounts:
    steps: int = 0
    drives: int = 0
    conflicts: int = 0  # a robot commanded by a leader that knew it did not own it (refused)
    late: int = 0  # a command from a robot's former owner that had not yet seen the truth of the change (refused)
    stale: int = 0  # drives computed from a truth older than STALE_DRIVE_S, or naming none or one not yet made (refused whole)
    robot_stale: int = 0  # DRIVEs a robot refused as computed from an observation older than its bound
    radio_commands: int = 0  # with --radio: robot commands sent to the arena's key, not the radio (refused)
    malformed: int = 0  # messages on the arena's keys that are not what docs/fleet-protocol.md says
    claims_granted: int = 0
    claims_repeated: int = 0  # a leader claiming a robot it owns already: answered yes, nothing changes
    claims_refused: int = 0
    handovers_refused: int = 0
    strangers: int = 0  # liveliness tokens under names that lead no team of this fleet (ignored)
    watchdog_stops: int = 0  # robots stopped by their own watchdog (their leader went quiet)
    contacts: int = 0  # steps on which two bodies came closer than CONTACT_M, centre to centre
    closest_m: float = math.inf  # the smallest centre-to-centre distance between two bodies so far


class Arena:
    """The shared world on the bus. ``step()`` is its loop's one step (the caller paces it)."""

    def __init__(self, scenario: FleetScenario, session: Any, fleet: str | None = None, radio: bool = False,
                 radio_drop: float = 0.0, radio_delay_s: float = 0.0, seed: int = 0,
                 radio_auth: RadioAuth | None = None) -> None:
        """``radio``: the robots take commands over an emulated radio (:attr:`radio`, one pty per
        leader, leader i's radio number i + 1, robot R<n> at address n), not from the bus;
        ``radio_auth``: the fleet's radio key the robots hold there (default: the open key)."""
        self.scenario = scenario
        self.fleet = fleet or scenario.name
        self.session = session
        self.state: ArenaState = initial_arena(scenario)
        self.ids = [ld.id for ld in scenario.leaders]
        n_robots = self.state.robots.shape[0]
        # the robots themselves (the followers' rules): each its scenario leader's at power-up
        self.robots = FollowerEmulator(list(range(1, n_robots + 1)), auth=radio_auth or RadioAuth())
        for r, i in enumerate(scenario.owners):
            a = r + 1
            self.robots.followers[a] = dataclasses.replace(self.robots.followers[a], owner=int(i) + 1,
                                                           lease_ms=START_LEASE_MS, lease_left_s=START_LEASE_MS / 1000)
        self.radio = Radio(len(self.ids), n_robots, radio_drop, radio_delay_s, seed, robots=self.robots) \
            if radio else None
        self._seq = 0
        self.owners: list[str | None] = [self.ids[i] for i in scenario.owners]
        self.leases = np.full(n_robots, START_LEASE_MS / 1000)
        self.command_age = np.full(n_robots, math.inf)  # since each robot's last obeyed command (its own clock)
        self.two_owners = 0
        self.owner_since = np.zeros(n_robots, dtype=np.int64)  # the first truth tick that shows each owner
        self.twists = np.zeros((len(self.ids), 2))
        self.twist_t = np.full(len(self.ids), -math.inf)
        self._leader_turn = math.radians(LEADER_TURN.hi)
        self.alive: set[str] = set()
        self.ever_alive: set[str] = set()
        self.counts = ArenaCounts()
        self.t = 0.0
        self.dt = 1.0 / scenario.rate_hz
        self.watchdog_stopped = np.zeros(n_robots, dtype=bool)
        self.gap_m = closest_distance(self.state)
        self._lock = threading.Lock()
        base = f"{root(self.fleet)}/arena"
        self._truth_pub = session.declare_publisher(f"{base}/truth", express=True)  # every step, at once
        self._event_pub = session.declare_publisher(f"{base}/events")
        self._token = session.liveliness().declare_token(f"{base}/alive")
        self._subs = [
            session.declare_subscriber(f"{base}/drive/*", self._on_drive),
            session.liveliness().declare_subscriber(f"{root(self.fleet)}/alive/*", self._on_alive, history=True),
        ]
        self._claims = session.declare_queryable(f"{base}/claim/*", self._on_claim)
        self._handovers = session.declare_queryable(f"{base}/handover", self._on_handover)

    # -- in ------------------------------------------------------------------------------------
    def _on_alive(self, sample: Any) -> None:
        leader = str(sample.key_expr).rsplit("/", 1)[-1]
        import zenoh

        if leader not in self.ids:  # a token under a name that leads no team: it can be given nothing
            if sample.kind == zenoh.SampleKind.PUT:
                with self._lock:
                    self.counts.strangers += 1
                self.event("stranger", f"a liveliness token for {leader[:40]!r}, which is not a leader of"
                                       f" {self.fleet}: ignored")
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(leader)
                self.ever_alive.add(leader)
            else:
                self.alive.discard(leader)
                orphans = [robot_name(r) for r, o in enumerate(self.owners) if o == leader]
        if sample.kind != zenoh.SampleKind.PUT:
            self.event("leader-lost", f"{leader}: its token is gone; orphans: {', '.join(orphans) or 'none'}")
        else:
            self.event("leader-joined", leader)

    def _on_drive(self, sample: Any) -> None:
        leader = str(sample.key_expr).rsplit("/", 1)[-1]
        try:
            msg = wire.obj(wire.decode(sample.payload.to_bytes()), "a drive", ("twist", "commands"),
                           ("tick", "truth_tick"))
            twist = wire.numbers(msg["twist"], 2, "twist")
            seen = msg.get("truth_tick")  # the newest truth the sender knew its robots by
            seen_tick = None if seen is None else wire.integer(seen, "truth_tick")
            if "tick" in msg:
                wire.integer(msg["tick"], "tick")
            commands = msg["commands"]
            if not isinstance(commands, dict):
                raise wire.BadMessage("commands must be an object {\"R<n>\": [v, w]}")
            parsed = []
            for name, vw in commands.items():
                r = robot_index(name, len(self.owners))
                if r is None:
                    raise wire.BadMessage(f"commands: {str(name)[:20]!r} is no robot of this arena")
                v, w = wire.numbers(vw, 2, f"commands.{name}")
                parsed.append((r, v, w))
        except wire.BadMessage:
            with self._lock:
                self.counts.malformed += 1
            return
        with self._lock:
            if leader not in self.ids:
                self.counts.malformed += 1
                return
            self.counts.drives += 1
            i = self.ids.index(leader)
            # computed from a truth older than STALE_DRIVE_S (a partition healing, a stalled sender) or
            # from none it names: no robot moves by it, nor the leader
            # (a tick the arena has not reached yet is no truth the sender saw: refused the same way)
            too_old = seen_tick is None or not 0 <= self.counts.steps - seen_tick <= STALE_DRIVE_S / self.dt
            if too_old:
                self.counts.stale += 1
            else:  # the world's physics: a leader's base within its limits
                self.twists[i] = (min(max(twist[0], -LEADER_SPEED.hi), LEADER_SPEED.hi),
                                  min(max(twist[1], -self._leader_turn), self._leader_turn))
                self.twist_t[i] = self.t
            dyn = self.scenario.dynamics
            age_ms = 0 if too_old or seen_tick is None else int((self.counts.steps - seen_tick) * self.dt * 1000)
            for r, v, w in parsed:
                if self.radio is not None:  # the robots listen to the radio only
                    self.counts.radio_commands += 1
                    continue
                if self.owners[r] != leader:
                    if seen_tick is not None and seen_tick < self.owner_since[r]:
                        self.counts.late += 1  # its former owner, before the truth told it: refused all the same
                    else:
                        self.counts.conflicts += 1
                    continue
                if too_old:
                    continue
                v = min(max(v, -dyn.speed_max_mps), dyn.speed_max_mps)  # a robot's body within its limits
                w = min(max(w, -dyn.turn_max_rps), dyn.turn_max_rps)
                self._drive(r, i + 1, age_ms, v, w)
            self._refresh()  # once for the whole message: what the robots now hold

    # -- the robots' own word (under the lock) ---------------------------------------------
    def _ask(self, frame: p.Frame) -> p.Frame | None:
        replies = self.robots.handle(frame)
        return replies[0] if replies else None

    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    def _drive(self, r: int, k: int, age_ms: int, v: float, w: float) -> None:
        """Leader number ``k``'s command to robot ``r`` as the robot takes it: a DRIVE. Its own
        lease lapsed (its drives were late for its length) and nobody took the robot: claimed
        again for it first, as a leader's serial link does on that NACK."""
        frame = p.drive(r + 1, self._next_seq(), k, age_ms, v, w)
        reply = self._ask(frame)
        if reply is not None and reply.msg_type == p.MSG_NACK:
            o = p.decode_ownership(reply)
            if o.reason == p.NACK_NOT_OWNER and o.owner == k:
                self._ask(p.claim(r + 1, self._next_seq(), k, LEASE_MS))
                reply = self._ask(frame)
        if reply is not None and reply.msg_type == p.MSG_NACK:
            o = p.decode_ownership(reply)
            if o.reason == p.NACK_STALE:
                self.counts.robot_stale += 1
            else:
                self.counts.conflicts += 1

    def _hand_over(self, r: int, to: str) -> str:
        """The operator's word, as robot ``r`` takes it: a HANDOVER to ``to`` from its owner (a
        CLAIM when it has none). "" when granted, else why not."""
        k_to = self.ids.index(to) + 1
        k_from = self.robots.snapshot()[r + 1].owner
        reply = self._ask(p.handover(r + 1, self._next_seq(), k_from, k_to, LEASE_MS) if k_from
                          else p.claim(r + 1, self._next_seq(), k_to, LEASE_MS))
        self._refresh()
        if reply is not None and reply.msg_type == p.MSG_OWNER:
            return ""
        return f"{robot_name(r)} refused it ({'no answer' if reply is None else p.decode_ownership(reply)})"

    def robot_commands(self, snap: dict[int, FollowerState] | None = None) -> FloatArray:
        """(R, 2) what each robot's wheels are set to, as body velocity (v m/s, w rad/s); from
        ``snap`` (the robots' states) when the caller has them already."""
        snap = snap if snap is not None else self.robots.snapshot()
        targets = np.array([(snap[r + 1].target_l_mps, snap[r + 1].target_r_mps) for r in range(len(self.owners))])
        return np.column_stack([targets.sum(axis=1) / 2, (targets[:, 1] - targets[:, 0]) / self.robots.hw.wheel_base_m])

    def _name(self, number: int) -> str | None:
        """A leader's radio number as its id (0: nobody; a number no leader of the fleet has:
        ``radio <n>``, a stranger on the radio)."""
        if number == 0:
            return None
        return self.ids[number - 1] if number <= len(self.ids) else f"radio {number}"

    def _refresh(self) -> None:
        """The owners, leases and command ages as the robots hold them (a change of owner is
        shown from the next truth on)."""
        snap = self.robots.snapshot()
        for r in range(len(self.owners)):
            f = snap[r + 1]
            name = self._name(f.owner)
            if name != self.owners[r]:
                self.owners[r] = name
                self.owner_since[r] = self.counts.steps + 1
            self.leases[r] = f.lease_left_s if f.lease_lives else 0.0
            self.command_age[r] = f.command_age_s
        self.two_owners = sum(f.two_owners for f in snap.values())

    def _on_claim(self, query: Any) -> None:
        """A claim on ``arena/claim/<id>`` is leader <id>'s (with fleet keys only <id> may ask
        there): a payload naming another leader is refused, never granted to either."""
        leader = str(query.key_expr).rsplit("/", 1)[-1]
        try:
            msg = wire.obj(wire.decode(query.payload.to_bytes() if query.payload is not None else None), "a claim",
                           ("robot",), ("leader",))
            named = wire.text(msg.get("leader", leader), "leader")
            r = robot_index(wire.text(msg["robot"], "robot"), len(self.owners))
            if r is None:
                raise wire.BadMessage(f"{msg['robot']!r} is no robot of this arena")
        except wire.BadMessage as exc:
            with self._lock:
                self.counts.malformed += 1
            query.reply(query.key_expr, json.dumps({"granted": False, "leader": leader, "why": f"{exc}; a claim is"
                                                    ' {"robot": "R<n>"} on arena/claim/<your id>',
                                                    "tick": self.counts.steps, "lease_left_ms": 0}))
            return
        lease_left_ms = 0
        with self._lock:
            owner = self.owners[r]
            repeated = False
            if named != leader:
                why = f"a claim on arena/claim/{leader} is {leader}'s, not {named[:40]!r}'s"
            elif leader not in self.ids:
                why = f"{leader[:40]!r} leads no team of {self.fleet}"
            elif self.radio is not None:
                why = "the robots are claimed over the radio (arena --radio)"
            elif leader not in self.alive:
                why = f"{leader} is not alive on the bus"
            elif owner is not None and owner != leader and owner in self.ids and owner not in self.ever_alive:
                why = f"{robot_name(r)} is {owner}'s, and {owner} has not joined yet"
            else:  # the robot says: granted once nobody's lease lives (its owner went quiet)
                reply = self._ask(p.claim(r + 1, self._next_seq(), self.ids.index(leader) + 1, LEASE_MS))
                self._refresh()
                if reply is not None and reply.msg_type == p.MSG_OWNER:
                    why, repeated = "", owner == leader
                else:
                    o = p.decode_ownership(reply) if reply is not None else p.Ownership(0, 0)
                    lease_left_ms = o.lease_left_ms
                    why = f"{robot_name(r)} is {self._name(o.owner)}'s, its lease lives {o.lease_left_ms} ms more"
            granted = why == ""
            if repeated:
                self.counts.claims_repeated += 1
            elif granted:
                self.counts.claims_granted += 1
            else:
                self.counts.claims_refused += 1
        query.reply(query.key_expr, json.dumps({"granted": granted, "robot": robot_name(r), "leader": leader,
                                                "why": why, "tick": self.counts.steps, "lease_left_ms": lease_left_ms}))
        self.event("claim", f"{robot_name(r)} to {leader}: " + ("granted" if granted else f"refused ({why})"))

    def _on_handover(self, query: Any) -> None:
        """The operator moves a robot to a leader (e.g. back to one that came back empty-handed):
        granted to a living leader with room, never leaving a living leader without a follower."""
        try:
            msg = wire.obj(wire.decode(query.payload.to_bytes() if query.payload is not None else None),
                           "a handover", ("robot", "to"), ("from",))
            to = wire.text(msg["to"], "to")
            r = robot_index(wire.text(msg["robot"], "robot"), len(self.owners))
            sender = wire.text(msg.get("from", "?"), "from")
            if r is None:
                raise wire.BadMessage(f"{msg['robot']!r} is no robot of this arena")
        except wire.BadMessage as exc:
            with self._lock:
                self.counts.malformed += 1
            query.reply(query.key_expr, json.dumps({"granted": False, "why": f"{exc}; a handover is"
                                                    ' {"robot": "R<n>", "to": ID, "from": WHO}',
                                                    "tick": self.counts.steps}))
            return
        with self._lock:
            owner = self.owners[r]
            mine = sum(1 for o in self.owners if o == to)
            if to not in self.alive:
                why = f"{to} is not alive on the bus"
            elif owner == to:
                why = f"{robot_name(r)} is {to}'s already"
            elif mine >= MAX_TEAM:
                why = f"{to} has {mine} followers, the most a team takes"
            elif owner is not None and owner in self.alive and sum(1 for o in self.owners if o == owner) <= 1:
                why = f"{robot_name(r)} is {owner}'s only follower"
            elif self.radio is not None:
                why = "on a radio only the robot's owner hands it over (a HANDOVER frame)"
            else:
                why = self._hand_over(r, to)
            granted = why == ""
            self.counts.handovers_refused += not granted
        query.reply(query.key_expr, json.dumps({"granted": granted, "robot": robot_name(r), "leader": to, "why": why,
                                                "tick": self.counts.steps}))
        self.event("handover", f"{robot_name(r)} from {owner} to {to} by {sender}: "
                               + ("granted" if granted else f"refused ({why})"))

    # -- out -----------------------------------------------------------------------------------
    def event(self, kind: str, detail: str) -> None:
        self._event_pub.put(json.dumps({"t": round(self.t, 3), "kind": kind, "detail": detail}))
        log.info("arena %s: %s", kind, detail)

    def truth(self) -> dict[str, Any]:
        s = self.state
        return {
            "fleet": self.fleet, "tick": self.counts.steps, "t": round(self.t, 4),
            "leaders": {lid: [round(float(v), 5) for v in s.leaders[i]] for i, lid in enumerate(self.ids)},
            "robots": [[round(float(v), 5) for v in pose] for pose in s.robots],
            "velocities": [[round(float(v), 5) for v in vel] for vel in s.robot_vel],
            "hues_deg": list(self.scenario.hues_deg), "owners": list(self.owners),
            "alive": sorted(self.alive), "lost": sorted(self.ever_alive - self.alive),
            "watchdog": [bool(b) for b in self.watchdog_stopped],
            "command_age": [round(float(a), 3) if math.isfinite(a) else None for a in self.command_age],
            "leases": [round(float(x), 3) for x in self.leases], "two_owners": self.two_owners,
            "radio": self.radio is not None,
            "conflicts": self.counts.conflicts, "late": self.counts.late, "stale": self.counts.stale,
            "closest_m": round(self.gap_m, 4), "contacts": self.counts.contacts, "refused": self.refused(),
        }

    def refused(self) -> dict[str, int]:
        """What the arena turned away so far, by kind (the fleet page shows it)."""
        c = self.counts
        return {"conflicts": c.conflicts, "late": c.late, "stale": c.stale + c.robot_stale, "malformed": c.malformed,
                "claims": c.claims_refused, "handovers": c.handovers_refused, "strangers": c.strangers,
                "radio_commands": c.radio_commands}

    # -- one step ------------------------------------------------------------------------------
    def step(self) -> None:
        with self._lock:
            snap = self.robots.snapshot()
            ages = np.array([snap[r + 1].command_age_s for r in range(len(self.owners))])
            commands = self.robot_commands(snap)  # the arena's bodies move as their wheels are set
            # a command that passes the watchdog's age during this step is zero for the whole step (the
            # robot's own watchdog would zero it within it; a robot never moves on one older than 0.5 s)
            stale = ages + self.dt > WATCHDOG_S + 1e-9
            newly = stale & ~self.watchdog_stopped & np.isfinite(ages)
            self.counts.watchdog_stops += int(newly.sum())
            self.watchdog_stopped = stale
            commands = np.where(stale[:, None], 0.0, commands)
            expired_before = self.t + self.dt - WATCHDOG_S - 1e-9
            twists = np.where((self.twist_t < expired_before)[:, None], 0.0, self.twists)
            self.state = step_arena(self.state, twists, commands, self.dt, self.scenario.dynamics)
            self.robots.step(self.dt)
            self.gap_m = closest_distance(self.state)
            self.counts.closest_m = min(self.counts.closest_m, self.gap_m)
            self.counts.contacts += int(self.gap_m < CONTACT_M)
            self.t += self.dt
            self.counts.steps += 1
            self._refresh()
            payload = json.dumps(self.truth(), separators=(",", ":"))
        self._truth_pub.put(payload)

    def run(self, stop: threading.Event) -> None:
        """Step at the scenario's rate until ``stop`` (late steps catch up, as the leaders' loop does)."""
        deadline = time.monotonic()
        while not stop.is_set():
            self.step()
            deadline += self.dt
            delay = deadline - time.monotonic()
            if delay < -3 * self.dt:
                deadline = time.monotonic()
            elif delay > 0:
                stop.wait(delay)

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self._claims.undeclare()
        self._handovers.undeclare()
        self._token.undeclare()
        if self.radio is not None:
            self.radio.close()
