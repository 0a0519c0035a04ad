"""The leader's part in orphan adoption (paper §6: "other leaders could adopt the 'orphan'
followers").

:class:`Adopter` watches the other leaders' liveliness tokens. When one goes, every survivor
runs :func:`core.fleet.adoption_plan` on the same truth; each claims from the arena only the
robots the plan gives it (the arena grants each robot once), then adds a slot to its own
formation for each robot granted: the loop takes the robot in on its next tick and drives it
to the new slot.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

import numpy as np

from core.fleet import MAX_TEAM, adoption_plan, slot_for_newcomer
from core.geometry import world_to_leader
from core.types import FloatArray

from app import wire
from app.backends.arena import ArenaTeam
from app.keys import follower_name, robot_index, robot_name, root
from app.params import ParamsStore

log = logging.getLogger(__name__)


class Adopter:
    """Claims this leader's share of a dead leader's robots and takes them into the team; takes
    in a robot the operator hands to this leader and lets go of one handed away."""

    def __init__(self, session: Any, fleet: str, leader_id: str, team: ArenaTeam, store: ParamsStore,
                 event: Any = None) -> None:
        self.session = session
        self.fleet = fleet
        self.leader_id = leader_id
        self.team = team
        self.store = store
        self.event = event or (lambda kind, detail: None)
        self.alive: set[str] = set()
        self.adopted: list[tuple[int, float]] = []  # (robot, monotonic time granted)
        self._changed_at: dict[int, int] = {}  # robot -> the arena tick of this leader's last change for it
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._adopting = threading.Lock()
        self._retry_at = float("inf")  # when the lease of a robot that refused a claim lapses
        self._wanted: set[int] = set()  # on a radio: robots claimed and not yet granted
        if team.link is not None:  # a robot granting our claim says so at once
            team.link.on_owned = lambda address: self._wake.set()
        self._sub = session.liveliness().declare_subscriber(f"{root(fleet)}/alive/*", self._on_alive, history=True)
        self._thread = threading.Thread(target=self._run, name="omniformation-adopter", daemon=True)
        self._thread.start()

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        leader = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(leader)
            else:
                self.alive.discard(leader)
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            # also looks once a second (a claim refused for a moment is tried again), and as soon as
            # a refused claim's lease has lapsed
            self._wake.wait(max(0.02, min(1.0, self._retry_at - time.monotonic())))
            self._wake.clear()
            if time.monotonic() >= self._retry_at:
                self._retry_at = float("inf")
            if self._stop.is_set():
                return
            try:
                self._sync()
            except Exception:
                log.exception("adoption failed")

    def _sync(self) -> None:
        """Orphans first (claim this leader's share), then follow the arena's word on who owns
        what: a robot the operator handed to this leader is taken in, one handed away is let go."""
        truth = self.team.latest_truth()
        if truth is None:
            return
        self._adopt_orphans(truth)
        truth = self.team.latest_truth() or truth
        tick = int(truth.get("tick", 0))
        owners: list[str | None] = list(truth["owners"])
        with self._lock:
            alive = set(self.alive)
        for r in list(self._wanted):  # on a radio: granted (the truth shows it), or another's after all
            if owners[r] == self.leader_id or (owners[r] in alive and truth.get("leases", [0] * len(owners))[r] > 0):
                self._wanted.discard(r)
                if owners[r] != self.leader_id:
                    self.team.unwant(r)
                    self.event("refused", f"claim for {robot_name(r)}: {owners[r]} holds it")
                else:
                    self._changed_at[r] = tick
                    self._take(r, truth, "adopted")
        for r, o in enumerate(owners):
            if o == self.leader_id and r in self.team.owned and self.team.emptied:  # its last one, handed back
                self.team.emptied = False
                self.team.want(r)
                self.event("handed over", f"{robot_name(r)}: {self.leader_id}'s again")
            if o == self.leader_id and r not in self.team.owned and tick > self._changed_at.get(r, -1):
                self._changed_at[r] = tick
                self._take(r, truth, "handed over")
        for r in list(self.team.owned):
            if r < len(owners) and owners[r] != self.leader_id and tick > self._changed_at.get(r, -1):
                self._changed_at[r] = tick
                self._release(r, truth, owners[r])

    def _adopt_orphans(self, truth: dict[str, Any]) -> None:
        with self._adopting:  # one claim round at a time: a robot taken is in the team before the next looks
            self._adopt_orphans_now(truth)

    def _adopt_orphans_now(self, truth: dict[str, Any]) -> None:
        with self._lock:
            alive = set(self.alive) | {self.leader_id}
        owners: list[str | None] = list(truth["owners"])
        lost = set(truth.get("lost", ())) - alive  # joined, and gone (as the arena and this leader both see it)
        # a robot this leader already took is no orphan, whatever an older truth still says of it:
        # claiming it again would be granted (it is ours) and seat it twice
        # (an emptied leader's last robot is not its own: it may be an orphan again, and the plan's to give)
        orphans = [r for r, o in enumerate(owners) if (o is None or o in lost) and r not in self._wanted
                   and (r not in self.team.owned or self.team.emptied)]
        if not orphans or set(truth.get("alive", ())) - alive:
            return  # nobody to adopt, or the arena knows of leaders this one has not heard of yet
        leaders = {lid: (float(pose[0]), float(pose[1]), sum(1 for o in owners if o == lid))
                   for lid, pose in truth["leaders"].items() if lid in alive}
        robots = np.asarray(truth["robots"], dtype=np.float64).reshape(-1, 3)
        plan = adoption_plan(orphans, robots[:, :2], leaders, MAX_TEAM)
        mine = [r for r, lid in plan.items() if lid == self.leader_id]
        for r in mine:
            granted_at = self._claim(r)
            if granted_at is not None:
                self._changed_at[r] = granted_at
                self._take(r, truth, "adopted")

    def _claim(self, r: int) -> int | None:
        """The arena's tick when it granted ``r`` to this leader, or None (refused, or no answer).
        On a radio the robot is asked (the link claims it until it grants or another holds it):
        None now, and it is taken in when the truth shows it granted."""
        if self.team.link is not None:
            self._wanted.add(r)
            self.team.want(r)
            return None
        payload = json.dumps({"leader": self.leader_id, "robot": robot_name(r)})
        for reply in self.session.get(f"{root(self.fleet)}/arena/claim/{self.leader_id}", payload=payload, timeout=2.0):
            try:
                answer = wire.decode(reply.ok.payload.to_bytes())
                if not isinstance(answer, dict):
                    raise wire.BadMessage("an answer is a JSON object")
            except (AttributeError, wire.BadMessage):
                continue
            tick = answer.get("tick", 0)
            if answer.get("granted") is True and robot_index(answer.get("robot"), 10_000) == r and wire.is_integer(tick):
                return int(tick)
            left = answer.get("lease_left_ms")
            if isinstance(left, int) and 0 < left <= 60_000:  # the robot's lease lives: ask again when it lapses
                self._retry_at = min(self._retry_at, time.monotonic() + left / 1000 + 0.05)
            self.event("refused", f"claim for {robot_name(r)}: {answer.get('why', '?')}")
        return None

    def _in_my_frame(self, truth: dict[str, Any], r: int) -> FloatArray:
        leader = np.asarray(truth["leaders"][self.leader_id], dtype=np.float64)
        robot = np.asarray(truth["robots"][r], dtype=np.float64)
        return np.asarray(world_to_leader(robot[None, :2], leader[:2], float(leader[2]))[0])

    def _take(self, r: int, truth: dict[str, Any], how: str) -> None:
        if r in self.team.owned:
            return  # in the team already: one slot per robot
        # a slot on the side it comes from (core.fleet.slot_for_newcomer), in this leader's frame
        here = self._in_my_frame(truth, r)
        current = self.store.get()
        slots = current.slots[:current.n_followers]
        rebuild = 0
        if self.team.emptied:  # the place its last robot (another's now) held is this one's: the loop
            for old in list(self.team.owned):  # makes its team afresh (a reset), this robot in it
                self.team.release(old)
            slots = slots[:0]
            self.team.emptied = False
            rebuild = 1
        robots, leaders = self.team.others()
        new_slot = slot_for_newcomer(slots, here, avoid=np.vstack([robots[np.hypot(*(robots - here).T) > 1e-6]
                                                                   if len(robots) else robots, leaders]))
        self.team.adopt(r)
        self.adopted.append((r, time.monotonic()))
        n = len(self.team.owned)
        self.store.fixed_followers = n
        self.store.update(f"fleet:{how} {robot_name(r)}", n_followers=n, slots=np.vstack([slots, new_slot]),
                          reset_requests=current.reset_requests + rebuild)
        self.event(how, f"{follower_name(n - 1, tuple(self.team.owned))}: now follower {n} of {self.leader_id}")
        log.info("%s %s (team of %d)", how, robot_name(r), n)

    def _release(self, r: int, truth: dict[str, Any], to: str | None) -> None:
        """The arena gave ``r`` to another leader: out of this team, with the slot nearest to it."""
        if len(self.team.owned) <= 1:  # its last: a team has one at least, so the loop keeps its place
            if not self.team.emptied:
                self.team.emptied = True
                self.team.unwant(r)
                self.event("released", f"{robot_name(r)}: now {to}'s; {self.leader_id} owns no robot and waits"
                                       " for the operator to hand one over")
                log.info("released %s to %s: no robot left", robot_name(r), to)
            return
        here = self._in_my_frame(truth, r)
        current = self.store.get()
        slots = current.slots[:current.n_followers]
        keep = np.ones(slots.shape[0], dtype=bool)
        keep[int(np.argmin(np.hypot(slots[:, 0] - here[0], slots[:, 1] - here[1])))] = False
        self.team.release(r)
        n = len(self.team.owned)
        self.store.fixed_followers = n
        self.store.update(f"fleet:handed over {robot_name(r)}", n_followers=n, slots=slots[keep])
        self.event("released", f"{robot_name(r)}: handed over to {to}; {self.leader_id} keeps {n}")
        log.info("released %s to %s (team of %d)", robot_name(r), to, n)

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(5.0)
        self._sub.undeclare()
