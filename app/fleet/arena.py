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
* a leader that joined and whose liveliness token is gone (process killed, network lost)
  leaves orphans: a **claim** by a living leader for an orphan is granted once (the first
  claim wins; the robot is then that leader's), any other claim is refused with the reason.
  The robots of a leader that has not joined yet are nobody's to take.

Key expressions and payloads: docs/fleet-protocol.md ("The arena").
"""

from __future__ import annotations

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
from core.link.protocol import WATCHDOG_S

from app.keys import robot_index, robot_name, root

log = logging.getLogger(__name__)

STALE_DRIVE_S = 0.5  # a drive computed from a truth older than this moves nothing
CONTACT_M = SafetySettings().min_distance_m  # two bodies' centres closer than this: the safety filter's limit broken


@dataclass
class ArenaCounts:
    steps: int = 0
    drives: int = 0
    conflicts: int = 0  # a robot commanded by a leader that knew it did not own it (refused)
    late: int = 0  # a command from a robot's former owner that had not yet seen the truth of the change (refused)
    stale: int = 0  # drives computed from a truth older than STALE_DRIVE_S, or naming none or one not yet made (refused whole)
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

    def __init__(self, scenario: FleetScenario, session: Any, fleet: str | None = None) -> None:
        self.scenario = scenario
        self.fleet = fleet or scenario.name
        self.session = session
        self.state: ArenaState = initial_arena(scenario)
        self.ids = [ld.id for ld in scenario.leaders]
        n_robots = self.state.robots.shape[0]
        self.owners: list[str | None] = [self.ids[i] for i in scenario.owners]
        self.commands = np.zeros((n_robots, 2))
        self.command_t = np.full(n_robots, -math.inf)  # arena time of each robot's last command
        self.commanded_by: list[str | None] = [None] * n_robots
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
            msg = json.loads(sample.payload.to_bytes())
            twist = [float(v) for v in msg["twist"]]
            commands = msg["commands"]
            seen = msg.get("truth_tick")  # the newest truth the sender knew its robots by
            seen_tick = int(seen) if isinstance(seen, int) and not isinstance(seen, bool) else None
            if len(twist) != 2 or not all(math.isfinite(v) for v in twist) or not isinstance(commands, dict):
                raise ValueError
            parsed = []
            for name, vw in commands.items():
                r = robot_index(name, len(self.owners))
                v, w = (float(x) for x in vw)
                if r is None or not (math.isfinite(v) and math.isfinite(w)):
                    raise ValueError
                parsed.append((r, v, w))
        except (ValueError, TypeError, KeyError, UnicodeDecodeError):
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
            for r, v, w in parsed:
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
                self.commands[r] = (v, w)
                self.command_t[r] = self.t
                self.commanded_by[r] = leader

    def _give(self, r: int, leader: str) -> None:
        """Robot ``r`` is ``leader``'s from the next truth on (under the lock): standing until its
        new owner's first command; nobody else's moves it."""
        self.owners[r] = leader
        self.owner_since[r] = self.counts.steps + 1
        self.commands[r] = 0.0
        self.commanded_by[r] = None

    def _on_claim(self, query: Any) -> None:
        """A claim on ``arena/claim/<id>`` is leader <id>'s (with fleet keys only <id> may ask
        there): a payload naming another leader is refused, never granted to either."""
        leader = str(query.key_expr).rsplit("/", 1)[-1]
        try:
            msg = json.loads(query.payload.to_bytes() if query.payload is not None else b"")
            named, r = str(msg.get("leader", leader)), robot_index(msg["robot"], len(self.owners))
            if r is None:
                raise ValueError
        except (ValueError, TypeError, KeyError, UnicodeDecodeError):
            with self._lock:
                self.counts.malformed += 1
            query.reply(query.key_expr, json.dumps({"granted": False, "why": "a claim is"
                                                    ' {"robot": "R<n>"} on arena/claim/<your id>'}))
            return
        with self._lock:
            owner = self.owners[r]
            repeated = False
            if named != leader:
                why = f"a claim on arena/claim/{leader} is {leader}'s, not {named[:40]!r}'s"
            elif leader not in self.alive:
                why = f"{leader} is not alive on the bus"
            elif owner == leader:
                why, repeated = "", True
            elif owner is not None and owner in self.alive:
                why = f"{robot_name(r)} is {owner}'s, and {owner} is alive"
            elif owner is not None and owner not in self.ever_alive:
                why = f"{robot_name(r)} is {owner}'s, and {owner} has not joined yet"
            else:  # its leader joined and is gone: an orphan
                why = ""
                self._give(r, leader)
            granted = why == ""
            if repeated:
                self.counts.claims_repeated += 1
            elif granted:
                self.counts.claims_granted += 1
            else:
                self.counts.claims_refused += 1
        query.reply(query.key_expr, json.dumps({"granted": granted, "robot": robot_name(r), "leader": leader,
                                                "why": why, "tick": self.counts.steps}))
        self.event("claim", f"{robot_name(r)} to {leader}: " + ("granted" if granted else f"refused ({why})"))

    def _on_handover(self, query: Any) -> None:
        """The operator moves a robot to a leader (e.g. back to one that came back empty-handed):
        granted to a living leader with room, never leaving a living leader without a follower."""
        try:
            msg = json.loads(query.payload.to_bytes() if query.payload is not None else b"")
            to, r = str(msg["to"]), robot_index(msg["robot"], len(self.owners))
            sender = str(msg.get("from", "?"))[:40]
            if r is None:
                raise ValueError
        except (ValueError, TypeError, KeyError, UnicodeDecodeError):
            with self._lock:
                self.counts.malformed += 1
            query.reply(query.key_expr, json.dumps({"granted": False, "why": "a handover is"
                                                    ' {"robot": "R<n>", "to": ID, "from": WHO}'}))
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
            else:
                why = ""
                self._give(r, to)
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
            "command_age": [round(float(a), 3) if math.isfinite(a) else None for a in self.t - self.command_t],
            "conflicts": self.counts.conflicts, "late": self.counts.late, "stale": self.counts.stale,
            "closest_m": round(self.gap_m, 4), "contacts": self.counts.contacts, "refused": self.refused(),
        }

    def refused(self) -> dict[str, int]:
        """What the arena turned away so far, by kind (the fleet page shows it)."""
        c = self.counts
        return {"conflicts": c.conflicts, "late": c.late, "stale": c.stale, "malformed": c.malformed,
                "claims": c.claims_refused, "handovers": c.handovers_refused, "strangers": c.strangers}

    # -- one step ------------------------------------------------------------------------------
    def step(self) -> None:
        with self._lock:
            # a command from before this is past the watchdog's age before this step ends: zero for the whole step
            expired_before = self.t + self.dt - WATCHDOG_S - 1e-9
            stale = self.command_t < expired_before
            newly = stale & ~self.watchdog_stopped & np.isfinite(self.command_t)
            self.counts.watchdog_stops += int(newly.sum())
            self.watchdog_stopped = stale
            commands = np.where(stale[:, None], 0.0, self.commands)
            twists = np.where((self.twist_t < expired_before)[:, None], 0.0, self.twists)
            self.state = step_arena(self.state, twists, commands, self.dt, self.scenario.dynamics)
            self.gap_m = closest_distance(self.state)
            self.counts.closest_m = min(self.counts.closest_m, self.gap_m)
            self.counts.contacts += int(self.gap_m < CONTACT_M)
            self.t += self.dt
            self.counts.steps += 1
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
