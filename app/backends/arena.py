"""A leader's team in a shared arena (``run --arena FLEET --leader-id ID``): a backend like the
simulated team and the real robots.

:class:`ArenaTeam` is a :class:`~app.contracts.Team` like the simulated one, but the world is
the arena's: its state is the newest truth the arena published (this leader's pose, the
robots it owns), and its commands and its own twist go to the arena as one drive message a
tick. Truth older than ``STALE_TRUTH_S`` is a lost link: the loop then commands zero.

The leader's part in orphan adoption (claims, slots for the robots taken in) is the fleet's:
app.fleet.adopter.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from core.fleet import slot_for_newcomer
from core.geometry import heading_world_to_leader, world_to_leader
from core.sim.team import TeamState, measure_followers
from core.types import BoolArray, Commands, FloatArray
from core.vision.freespace import Scan

from app.contracts import Feedback, Observation

if TYPE_CHECKING:
    from app.backends.serial_link import SerialLink
from app.keys import robot_name, root

log = logging.getLogger(__name__)

STALE_TRUTH_S = 0.3  # no truth for this long: the arena (the robots' channel) is lost
TICK_SLACK_S = 1.0  # a truth's tick runs ahead of the arena's clock by at most this (and 25 %) since the last
TRUTH_QUEUE = 64  # truths held for the leader between two reads (2 s at 30 Hz); the oldest go first when it is full


def read_truth(msg: Any) -> dict[str, Any]:
    """A truth as docs/fleet-protocol.md gives it, every field a leader reads of its exact type
    (app.wire), else BadMessage."""
    from app import wire

    truth = wire.obj(msg, "a truth", ("tick", "t", "leaders", "robots", "owners"), more=True)
    wire.integer(truth["tick"], "tick")
    wire.number(truth["t"], "t")
    if not isinstance(truth["leaders"], dict):
        raise wire.BadMessage("leaders must be an object {ID: [x, y, theta]}")
    for lid, pose in truth["leaders"].items():
        wire.check_numbers(pose, 3, f"leaders.{str(lid)[:32]}")
    robots = truth["robots"]
    if not isinstance(robots, list):
        raise wire.BadMessage("robots must be a list of [x, y, theta]")
    for pose in robots:
        wire.check_numbers(pose, 3, "robots")
    for name, width in (("velocities", 2), ("leases", 0)):
        if name in truth:
            values = truth[name]
            if not isinstance(values, list) or len(values) != len(robots):
                raise wire.BadMessage(f"{name} must be a list with one entry per robot")
            if width:
                for v in values:
                    wire.check_numbers(v, width, name)
            else:
                wire.check_numbers(values, len(values), name)
    owners = truth["owners"]
    if not isinstance(owners, list) or len(owners) != len(robots) or \
            not all(o is None or isinstance(o, str) for o in owners):
        raise wire.BadMessage("owners must be a list of ids (or null) with one entry per robot")
    for name in ("alive", "lost"):
        if name in truth and not (isinstance(truth[name], list) and all(isinstance(x, str) for x in truth[name])):
            raise wire.BadMessage(f"{name} must be a list of ids")
    return truth


class NoArena(RuntimeError):
    pass


class ArenaTeam:
    """This leader's robots, as the arena tells them."""

    def __init__(self, session: Any, fleet: str, leader_id: str, position_noise_m: float, heading_noise_rad: float,
                 seed: int, wait_s: float = 10.0, hues_deg: tuple[float, ...] = (), rate_hz: float = 30.0) -> None:
        """``hues_deg``: every robot's marker hue, in robot order (the fleet scenario's): what
        this leader's camera draws and the pipeline looks for. ``rate_hz``: the arena's step rate
        (the fleet scenario's): a truth's tick never runs ahead of it."""
        self.session = session
        self.hues_deg = tuple(hues_deg)
        self.fleet = fleet
        self.leader_id = leader_id
        self.position_noise_m = position_noise_m
        self.heading_noise_rad = heading_noise_rad
        self.rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._truth: dict[str, Any] | None = None
        self._arrays: tuple[dict[str, Any], tuple[FloatArray, FloatArray, FloatArray, FloatArray]] | None = None  # (a truth, _read's arrays of it)
        self._truth_at = -math.inf  # the truth taken last came after this (its age)
        self._taken_at = -math.inf  # and was read then (the next one's allowance)
        self.rate_hz = rate_hz
        self._refused = 0  # truths not of the protocol's shape, or whose tick the arena's clock cannot have reached
        self._reading = threading.Lock()  # one reader at a time takes the queued truths, so they are taken in order
        # the truths wait in zenoh's queue until they are read (each tick), not in a callback of ours: a
        # callback is a thread woken and the interpreter's lock taken 30 times a second, which cost a
        # vision leader more CPU than reading the truths (and took the lock from its loop mid-tick)
        import zenoh

        self._emptied_at = time.monotonic()  # when the queue was last found empty (see _read_queued)
        self._closed = False
        self._sub = session.declare_subscriber(f"{root(fleet)}/arena/truth", zenoh.handlers.RingChannel(TRUTH_QUEUE))
        self._drive: Any = None  # declared at the first command: a leader refused at start-up never drives
        # no truth at once: is an arena alive at all (its token)? None: say so now, not after wait_s
        if not self._wait_truth(min(wait_s, 2.0)) and not any(
                getattr(r, "ok", None) is not None
                for r in session.liveliness().get(f"{root(fleet)}/arena/alive", timeout=1.0)):
            self._sub.undeclare()
            raise NoArena(f"no arena is alive on fleet {fleet}'s bus (its token {root(fleet)}/arena/alive): start"
                          f" `omniformation arena` first, and connect to it (--zenoh-connect)")
        if not self._wait_truth(wait_s):
            self._sub.undeclare()
            raise NoArena(f"no arena publishes {root(fleet)}/arena/truth (waited {wait_s:g} s): start"
                          f" `omniformation arena` first, and connect to it (--zenoh-connect)")
        truth = self._truth
        assert truth is not None
        if leader_id not in truth["leaders"]:
            self._sub.undeclare()
            raise NoArena(f"leader id {leader_id!r} is not one of the arena's leaders ({', '.join(truth['leaders'])})")
        self.owned: list[int] = [r for r, o in enumerate(truth["owners"]) if o == leader_id]  # in the order taken
        self.active: list[int] = list(self.owned)  # the robots the loop drives (owned ones, up to the team's size)
        self._twist: tuple[float, float] = (0.0, 0.0)
        self._tick: int = 0
        self.state: TeamState = self._state_from(truth)
        self.link: SerialLink | None = None  # with a radio: the robots' link (the arena gives only the world)
        # every robot it had is another's now (adopted while it was cut off): the loop keeps the last
        # one's place (a team has one at least), commands it nothing, and the state is an empty team
        self.emptied: bool = False

    def use_radio(self, port: str, radio_id: int, baud: int = 115200, **auth: Any) -> None:
        """Command the robots over a radio (`arena --radio`): this leader's serial link with its
        radio id claims the robots it owns and drives them (protocol 2, DRIVE with the
        observation's age); the arena's drive key carries only this leader's own twist. ``auth``:
        SerialLink's radio_key, sender_id, allow_unauthenticated and counter (protocol 3)."""
        from app.backends.serial_link import SerialLink

        self.link = SerialLink(port, 0, baud, addresses=[r + 1 for r in self.owned], radio_id=radio_id, **auth)

    # -- truth in --------------------------------------------------------------------------
    def _read_queued(self) -> None:
        """Take or refuse, in their order, the truths that came since the last read. Each came
        after the queue was last found empty: its age counts from then, so a truth that waited
        in the queue is never taken for younger than it is."""
        with self._reading:
            while not self._closed:  # (closed: its subscriber is gone, and the last truth taken stands)
                checked = time.monotonic()
                sample = self._sub.try_recv()
                if sample is None:
                    self._emptied_at = checked  # whatever is queued next came after this
                    return
                self._on_truth(sample, self._emptied_at)

    def _wait_truth(self, wait_s: float) -> bool:
        """Whether a truth was taken within ``wait_s`` (start-up)."""
        deadline = time.monotonic() + wait_s
        while True:
            taken = self.latest_truth() is not None  # (the queued ones read first)
            if taken or time.monotonic() >= deadline:
                return taken
            time.sleep(0.01)

    @property
    def truths_refused(self) -> int:
        """Messages on the truth key not taken (not of the protocol's shape, or naming a tick the
        arena's clock cannot have reached, ...), the queued ones read first."""
        self._read_queued()
        return self._refused

    def _on_truth(self, sample: Any, came_after: float) -> None:
        """The arena's word, if it is a truth and its tick one the arena's clock can have reached
        since the last one (ahead by at most the time gone, 25 % and TICK_SLACK_S more, at the
        scenario's rate), naming this leader and as many robots as the first one did (an arena's
        leaders and robots are its fleet file's); anything else is counted and dropped
        (docs/fleet-protocol.md, "truth"). The first truth is checked for this leader at start.
        It came after ``came_after`` and by now: the allowance counts the time to now (the most
        the arena's clock can have gone), its age from ``came_after`` (never less than it is)."""
        from app import wire

        truth: dict[str, Any] | None
        try:
            truth = read_truth(wire.decode(sample.payload.to_bytes()))
        except wire.BadMessage as exc:
            self._refuse_truth(str(exc))
            return
        now, why = time.monotonic(), ""
        with self._lock:
            last = self._truth
            if last is not None and truth is not None:
                ahead = self.rate_hz * (1.25 * (now - self._taken_at) + TICK_SLACK_S)
                if not last["tick"] < truth["tick"] <= last["tick"] + ahead:
                    why = f"tick {truth['tick']} after {last['tick']} {now - self._taken_at:.2f} s ago"
                    truth = None
                elif self.leader_id not in truth["leaders"]:  # the arena's leaders are its fleet file's
                    why = f"it names no leader {self.leader_id!r}"
                    truth = None
                elif len(truth["robots"]) != len(last["robots"]):  # and so are its robots
                    why = f"{len(truth['robots'])} robots where the arena has {len(last['robots'])}"
                    truth = None
            if truth is not None:
                self._truth = truth
                self._taken_at = now  # read: the next truth's allowance counts from here
                self._truth_at = came_after  # came: its age counts from here
        if truth is None:
            self._refuse_truth(why)

    def _refuse_truth(self, why: str) -> None:
        self._refused += 1
        if self._refused in (1, 10, 100, 1000):
            log.warning("%d message(s) on the arena's truth key refused (%s)", self._refused, why)

    def latest_truth(self) -> dict[str, Any] | None:
        """The newest truth taken, the queued ones read first."""
        self._read_queued()
        with self._lock:
            return self._truth

    def _read(self, truth: dict[str, Any]) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Of ``truth``, as arrays: this leader's pose (3,), every robot (R, 3) and their velocities
        (R, 2) in the arena's frame, and every robot then every other leader (R + L - 1, 3) in this
        leader's frame. Made once per truth (the state, the camera's scene and the filter's other
        bodies all read it each tick), read-only."""
        cached = self._arrays
        if cached is not None and cached[0] is truth:
            return cached[1]
        me = np.asarray(truth["leaders"][self.leader_id], dtype=np.float64)
        robots = np.asarray(truth["robots"], dtype=np.float64).reshape(-1, 3)
        vel = np.asarray(truth.get("velocities", np.zeros((robots.shape[0], 2))), dtype=np.float64).reshape(-1, 2)
        leaders = np.array([pose for lid, pose in truth["leaders"].items() if lid != self.leader_id],
                           dtype=np.float64).reshape(-1, 3)
        bodies = np.vstack([robots, leaders])
        xy = np.asarray(world_to_leader(bodies[:, :2], me[:2], float(me[2]))).reshape(-1, 2)
        here = np.column_stack([xy, heading_world_to_leader(bodies[:, 2], float(me[2]))])
        arrays = (me, robots, vel, here)
        for a in arrays:
            a.flags.writeable = False
        self._arrays = (truth, arrays)  # one assignment: a reader on another thread sees the old pair or this one
        return arrays

    def _state_from(self, truth: dict[str, Any]) -> TeamState:
        me, robots, vel, _ = self._read(truth)
        idx = np.asarray(self.active, dtype=np.int64)
        return TeamState(me.copy(), robots[idx], vel[idx])  # (fancy indexing copies)

    def resize(self, n: int) -> None:
        """Drive the first ``n`` robots this leader owns (the loop's team size)."""
        self.active = self.owned[:n]
        truth = self.latest_truth()
        if truth is not None:
            self.state = self._state_from(truth)

    def adopt(self, robot: int) -> None:
        if robot not in self.owned:
            self.owned.append(robot)
        self.want(robot)

    def want(self, robot: int) -> None:
        """On a radio: claim ``robot`` (again and again until it grants it)."""
        if self.link is not None:
            self.link.want(robot + 1)

    def unwant(self, robot: int) -> None:
        """On a radio: stop claiming or driving ``robot``."""
        if self.link is not None:
            self.link.let_go(robot + 1)

    def others(self) -> tuple[FloatArray, FloatArray]:
        """(robots (k, 2), leaders (m, 2)) in this leader's frame: every body of the arena that
        is not this leader or one of the robots it drives."""
        truth = self.latest_truth()
        if truth is None:
            return np.zeros((0, 2)), np.zeros((0, 2))
        here, n_robots = self._read(truth)[3], len(truth["robots"])  # every robot, then every other leader
        robots, leaders = here[:n_robots], here[n_robots:]
        keep = np.ones(robots.shape[0], dtype=bool)
        keep[[r for r in self.active if r < robots.shape[0]]] = False
        return robots[keep, :2], leaders[:, :2].copy()

    # -- what this leader's camera sees (vision in the arena) --------------------------------
    def scene(self) -> FloatArray:
        """Every robot, then every other leader: (R + L - 1, 3) poses (x, y, a) in this
        leader's frame, from the newest truth; the team's state moves to the same truth, so the
        camera's floor and its bodies agree."""
        truth = self.latest_truth()
        assert truth is not None
        self.state = self._state_from(truth)
        return self._read(truth)[3].copy()  # the truth's bodies here, already in scene order

    def scene_hues(self) -> tuple[float, ...]:
        """The marker hue of each body of :meth:`scene` (NaN: a leader, no marker)."""
        truth = self.latest_truth()
        assert truth is not None
        return self.hues_deg + (math.nan,) * (len(truth["leaders"]) - 1)

    def team_hues(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(the hues of the robots this leader drives, in the team's order; every other robot's)."""
        own = tuple(self.hues_deg[r] for r in self.active)
        return own, tuple(h for r, h in enumerate(self.hues_deg) if r not in self.active)

    def wait_for_robots(self, poll_s: float = 0.2) -> None:
        """Until the arena says this leader owns a robot (an operator handed one over): a leader
        that comes back after its robots were adopted starts empty-handed."""
        while not self.owned:
            time.sleep(poll_s)
            truth = self.latest_truth()
            if truth is not None:
                self.owned = [r for r, o in enumerate(truth["owners"]) if o == self.leader_id]
        self.active = list(self.owned)
        truth = self.latest_truth()
        assert truth is not None
        self.state = self._state_from(truth)

    def slots_for_owned(self) -> FloatArray:
        """A formation for the robots this leader owns now, each on the side it stands, clear
        of the other teams (a leader that was handed robots after it came back)."""
        truth = self.latest_truth()
        assert truth is not None
        me = np.asarray(truth["leaders"][self.leader_id], dtype=np.float64)
        robots = np.asarray(truth["robots"], dtype=np.float64).reshape(-1, 3)
        here = np.asarray(world_to_leader(robots[self.owned, :2], me[:2], float(me[2]))).reshape(-1, 2)
        others, leaders = self.others()
        slots = np.zeros((0, 2))
        for xy in here:
            slots = np.vstack([slots, slot_for_newcomer(slots, xy, avoid=np.vstack([others, leaders]))])
        return slots

    def release(self, robot: int) -> None:
        if robot in self.owned:
            self.owned.remove(robot)
        self.unwant(robot)

    # -- the Team contract ----------------------------------------------------------------
    @property
    def link_state(self) -> str:
        self._read_queued()  # a truth that came is not missing
        age = time.monotonic() - self._truth_at
        if age > STALE_TRUTH_S:
            return f"arena: no truth for {age:.1f} s"
        return "arena" if self.link is None else f"arena; radio {self.link.link_state}"

    @property
    def link_lost(self) -> bool:
        self._read_queued()
        return time.monotonic() - self._truth_at > STALE_TRUTH_S or (self.link is not None and self.link.lost)

    def answering(self) -> BoolArray:
        """The robots the newest truth says are this leader's (its truth is the robots' link). A
        robot the arena gave to another leader (after a partition, a handover) is not: the loop
        counts it untracked and commands it nothing from that tick, before the adopter lets it
        go from the formation."""
        truth = self.latest_truth()
        owners = truth["owners"] if truth is not None else []
        mine = np.array([r < len(owners) and owners[r] == self.leader_id for r in self.active[:self.state.n]],
                        dtype=bool)
        if self.link is not None:  # on a radio: and the robot answers this leader as its owner
            mine &= self.link.answering_at([r + 1 for r in self.active[:self.state.n]])
        return mine

    def link_detail(self) -> str:
        robots = f"arena {self.fleet}: robots {', '.join(robot_name(r) for r in self.active)}"
        return robots if self.link is None else f"{robots}; radio: {self.link.detail()}"

    def observe(self) -> tuple[FloatArray, FloatArray, BoolArray]:
        truth = self.latest_truth()
        if truth is not None:
            self.state = self._state_from(truth)
        p, a = measure_followers(self.state, self.rng, self.position_noise_m, self.heading_noise_rad)
        return p, a, np.ones(len(a), dtype=bool)

    def truth(self) -> tuple[FloatArray, FloatArray]:
        return measure_followers(self.state, self.rng)

    @property
    def leader_link(self) -> None:
        """The arena moves this leader: no base of its own to measure."""
        return None

    def radio_delay_s(self) -> None:
        """The arena's robots: no camera-to-radio latency to bridge (the truth is the arena's)."""
        return None

    def send(self, commands: Commands) -> None:
        v, w = np.asarray(commands.v, dtype=np.float64), np.asarray(commands.w, dtype=np.float64)
        truth = self.latest_truth()
        owners = truth["owners"] if truth is not None else []
        # only the robots the arena says are this leader's: one another leader was granted is never commanded
        mine = [(k, r) for k, r in enumerate(self.active) if k < len(v) and r < len(owners) and owners[r] == self.leader_id]
        if self.link is not None:  # on a radio the robots take it from there (each refuses what is not its owner's)
            k_n = min(len(self.active), len(v))
            self.link.send(Commands(v[:k_n], w[:k_n], commands.observed_at), [r + 1 for r in self.active[:k_n]])
            mine = []
        payload = {"tick": self._tick, "truth_tick": int(truth["tick"]) if truth is not None else None,
                   "twist": [round(self._twist[0], 6), round(self._twist[1], 6)],
                   "commands": {robot_name(r): [round(float(v[k]), 6), round(float(w[k]), 6)] for k, r in mine}}
        self._tick += 1
        if self._drive is None:
            self._drive = self.session.declare_publisher(f"{root(self.fleet)}/arena/drive/{self.leader_id}",
                                                      express=True)  # every tick, at once
        self._drive.put(json.dumps(payload, separators=(",", ":")))

    def advance(self, leader_twist: tuple[float, float], dt: float, t: float) -> None:
        self._twist = (float(leader_twist[0]), float(leader_twist[1]))  # goes with the next tick's commands

    def close(self) -> None:
        if self._closed:
            return
        if self._drive is not None:  # it drove: its robots and itself to zero, as the last word
            self._twist = (0.0, 0.0)
            self.send(Commands.zeros(len(self.active)))
            self._drive.undeclare()
        if self.link is not None:
            self.link.close()  # STOP to the robots it owns
        with self._reading:  # a reader on another thread (the adopter's) finishes first, and none reads after
            self._closed = True
            self._sub.undeclare()


OTHER_ROBOT_RING_M = 0.10  # another team's robot, as the filter sees it: a ring of points this far out
OTHER_LEADER_RING_M = 0.20  # another leader likewise (it is larger)


def body_rings(centres: FloatArray, radius_m: float, points: int = 8) -> FloatArray:
    """(k * points, 2) points on a circle of ``radius_m`` round each centre."""
    ang = np.linspace(0.0, 2 * np.pi, points, endpoint=False)
    ring = radius_m * np.column_stack([np.cos(ang), np.sin(ang)])
    return np.asarray((centres[:, None, :] + ring[None, :, :]).reshape(-1, 2), dtype=np.float64)


class ArenaFeedback:
    """The team's poses from ``inner`` (the arena's truth plus noise, a TruthFeedback, or this
    leader's camera rendered from the arena and the vision pipeline), and every body that is
    not this team's (other teams' robots, orphans, other leaders) as obstacle points the safety
    filter keeps clear of: rings the size of each body, so two robots of different teams keep
    the filter's distance from each other as two of one team do. Those bodies come from the
    arena's truth, as the other leaders' published states would give them in a real fleet."""

    def __init__(self, team: ArenaTeam, inner: Feedback) -> None:
        self.team = team
        self.inner = inner

    def observe(self, dt: float, commands: FloatArray, error_norm: FloatArray) -> Observation:
        obs = self.inner.observe(dt, commands, error_norm)
        robots, leaders = self.team.others()
        points = np.vstack([body_rings(robots, OTHER_ROBOT_RING_M), body_rings(leaders, OTHER_LEADER_RING_M)])
        if obs.obstacles is not None and len(obs.obstacles):  # the camera's own free-space scan too
            points = np.vstack([points, obs.obstacles])
        return dataclasses.replace(obs, obstacles=points if len(points) else None)

    def scan_after(self) -> Scan | None:
        """The camera's free-space scan, when ``inner`` is a camera and one is due."""
        return self.inner.scan_after()

    @property
    def scan_pending(self) -> bool:
        return bool(self.inner.scan_pending)
