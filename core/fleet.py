"""A fleet (paper §6): several leaders, each with a team, in one arena; what a fleet scenario
says; one step of the shared world; and the rule that gives a dead leader's followers to
the living ones.

"A large robot group divide[s] itself into smaller teams each having one leader. … other
leaders could adopt the 'orphan' followers." The arena (app/fleet/arena.py) steps the world
below and tells every leader the truth; who may command which robot is the arena's to say,
so two leaders never command one robot. When a leader dies, every survivor runs
:func:`adoption_plan` on the same truth and claims only the robots the plan gives it.

Robots are numbered fleet-wide (0 … R−1, shown as R1 … RR); each carries one marker hue,
fleet-wide distinct (a leader's camera sees the other teams too), at least
MIN_HUE_SEPARATION_DEG apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.bounds import LEADER_SPEED, LEADER_TURN
from core.camera.config import MIN_HUE_SEPARATION_DEG, hue_distance_deg
from core.config import ConfigError, parse_dynamics, toml_document
from core.control.presets import MIN_SPACING_M, PRESET_REACH_M, default_formation
from core.geometry import heading_leader_to_world, leader_to_world
from core.sim.team import FollowerDynamics, followers_kernel, integrate_unicycle
from core.types import FloatArray, IntArray

LEADER_MODES = ("stop", "straight", "circle")
MAX_TEAM = 8  # a leader's team at most (the page's follower limit)
NO_OWNER = -1
ARENA_LIMIT_M = 50.0
START_SPREAD = 1.3  # followers start this much farther out than their slots, heading as the leader


@dataclass(frozen=True)
class FleetLeader:
    id: str
    start: tuple[float, float, float]  # world x, y (m), heading (rad, from +x)
    followers: int
    mode: str  # stop | straight | circle: how it drives once its team is in formation
    speed_mps: float
    turn_deg_s: float
    hues_deg: tuple[float, ...]  # its followers' marker hues


@dataclass(frozen=True)
class FleetScenario:
    name: str
    description: str
    leaders: tuple[FleetLeader, ...]
    rate_hz: float
    dynamics: FollowerDynamics

    @property
    def robots(self) -> int:
        return sum(ld.followers for ld in self.leaders)

    @property
    def hues_deg(self) -> tuple[float, ...]:
        """Every robot's marker hue, in robot order."""
        return tuple(h for ld in self.leaders for h in ld.hues_deg)

    @property
    def owners(self) -> IntArray:
        """(R,) the leader (index) each robot starts with."""
        return np.repeat(np.arange(len(self.leaders)), [ld.followers for ld in self.leaders])

    def leader_index(self, leader_id: str) -> int:
        for i, ld in enumerate(self.leaders):
            if ld.id == leader_id:
                return i
        raise KeyError(leader_id)


def spread_hues(count: int, first_deg: float = 0.0) -> tuple[float, ...]:
    """``count`` hues evenly round the colour circle."""
    return tuple(round((first_deg + 360.0 * k / count) % 360.0, 3) for k in range(count))


def parse_fleet(text: str, source: str) -> FleetScenario:
    """A fleet scenario (static_config/fleets/*.toml); ConfigError (one line) on anything wrong,
    clashing marker hues included."""
    top = toml_document(text, source)
    name = top.text("name")
    description = top.text("description", default="")
    rate = top.number("rate_hz", 1.0, 200.0, default=30.0, unit="Hz")
    dynamics = parse_dynamics(top.table("dynamics"))
    tables = top.tables("leaders")
    if not tables:
        raise top.fail("leaders", [], "at least one [[leaders]] table")
    raw: list[tuple[str, tuple[float, float, float], int, str, float, float, tuple[float, ...] | None]] = []
    for lt in tables:
        lid = lt.text("id")
        if not (1 <= len(lid) <= 32 and all(c.isalnum() or c in "_-" for c in lid) and lid.isascii()):
            raise lt.fail("id", lid, "1 to 32 characters of A-Z, a-z, 0-9, _ and -")
        x, y = lt.point("start", ARENA_LIMIT_M)
        heading = math.radians(lt.number("heading_deg", -360.0, 360.0, default=90.0, unit="deg"))
        n = lt.integer("followers", 1, MAX_TEAM)
        mode = lt.text("mode", default="straight", choices=LEADER_MODES)
        speed = lt.bounded("speed_mps", LEADER_SPEED, default=0.04)
        turn = lt.bounded("turn_deg_s", LEADER_TURN, default=0.0)
        hues: tuple[float, ...] | None = None
        if lt.has("hues_deg"):
            value = lt.raw("hues_deg")
            if (not isinstance(value, list) or len(value) != n
                    or not all(isinstance(h, (int, float)) and not isinstance(h, bool) and 0 <= h < 360 for h in value)):
                raise lt.fail("hues_deg", value, f"a list of {n} hues in [0, 360) deg, one per follower")
            hues = tuple(float(h) for h in value)
        lt.finish()
        raw.append((lid, (x, y, heading), n, mode, speed, turn, hues))
    ids = [r[0] for r in raw]
    for i, lid in enumerate(ids):
        if lid in ids[:i]:
            raise ConfigError(f"{source}: leaders[{i + 1}].id = {lid!r}: leaders[{ids.index(lid) + 1}] has it already;"
                              " every leader needs its own id")
    given = [r[6] for r in raw]
    if any(h is not None for h in given) and not all(h is not None for h in given):
        raise ConfigError(f"{source}: hues_deg is given for some leaders only: give it for every leader or for none"
                          " (then the hues are spread evenly fleet-wide)")
    total = sum(r[2] for r in raw)
    if total * MIN_HUE_SEPARATION_DEG > 360.0:
        raise ConfigError(f"{source}: {total} followers cannot carry hues {MIN_HUE_SEPARATION_DEG:g} deg apart"
                          f" (at most {int(360 // MIN_HUE_SEPARATION_DEG)} in one fleet)")
    hues_all = list(spread_hues(total)) if given[0] is None else [h for g in given if g is not None for h in g]
    owners = [r[0] for r in raw for _ in range(r[2])]
    for i in range(total):
        for j in range(i + 1, total):
            gap = hue_distance_deg(hues_all[i], hues_all[j])
            if gap < MIN_HUE_SEPARATION_DEG:
                raise ConfigError(
                    f"{source}: robots R{i + 1} ({owners[i]}) and R{j + 1} ({owners[j]}) have hues {hues_all[i]:g} and"
                    f" {hues_all[j]:g} deg, {gap:g} deg apart; marker hues are fleet-wide and need at least"
                    f" {MIN_HUE_SEPARATION_DEG:g} deg between any two (every camera sees every team)")
    top.finish()
    leaders = []
    k = 0
    for lid, start, n, mode, speed, turn, _ in raw:
        leaders.append(FleetLeader(lid, start, n, mode, speed, turn, tuple(hues_all[k:k + n])))
        k += n
    return FleetScenario(name, description, tuple(leaders), rate, dynamics)


@dataclass(frozen=True)
class ArenaState:
    """The shared world: every leader's and every robot's pose (world frame)."""

    leaders: FloatArray  # (L, 3) x, y, theta
    robots: FloatArray  # (R, 3) x, y, theta
    robot_vel: FloatArray  # (R, 2) actual v, w


def initial_arena(scenario: FleetScenario) -> ArenaState:
    """Leaders where the scenario puts them; each team spread a little beyond its formation."""
    leaders = np.array([ld.start for ld in scenario.leaders], dtype=np.float64)
    robots = []
    for ld in scenario.leaders:
        p = default_formation(ld.followers) * START_SPREAD
        xy = leader_to_world(p, np.asarray(ld.start[:2]), ld.start[2])
        th = heading_leader_to_world(np.full(ld.followers, math.pi / 2), ld.start[2])
        robots.append(np.column_stack([xy, th]))
    r = np.vstack(robots)
    return ArenaState(leaders, r, np.zeros((r.shape[0], 2)))


def step_arena(state: ArenaState, leader_twists: FloatArray, robot_commands: FloatArray, dt: float,
               dynamics: FollowerDynamics) -> ArenaState:
    """Every leader by its twist (L, 2), every robot by its command (R, 2), one dt."""
    r = state.robots.shape[0]
    out_poses = np.empty((r, 3))
    out_vel = np.empty((r, 2))
    followers_kernel(np.ascontiguousarray(state.robots), np.ascontiguousarray(state.robot_vel),
                     np.ascontiguousarray(robot_commands[:, 0], dtype=np.float64),
                     np.ascontiguousarray(robot_commands[:, 1], dtype=np.float64), float(dt), dynamics.as_array(),
                     np.zeros(r, dtype=np.bool_), np.zeros((r, 2)), out_poses, out_vel)
    leaders = integrate_unicycle(state.leaders, leader_twists[:, 0], leader_twists[:, 1], dt)
    return ArenaState(leaders, out_poses, out_vel)


def adoption_plan(orphans: list[int], robot_xy: FloatArray, leaders: dict[str, tuple[float, float, int]],
                  capacity: int = MAX_TEAM) -> dict[int, str]:
    """Who adopts each orphan: robots in number order, each to the nearest living leader with
    room left (``leaders``: id -> (x, y, followers it has now)), ties by id. Every leader that
    runs this on the same truth gets the same answer; a robot no leader has room for is left out."""
    count = {lid: c for lid, (_, _, c) in leaders.items()}
    plan: dict[int, str] = {}
    for r in sorted(orphans):
        rooms = [(math.hypot(float(robot_xy[r, 0]) - x, float(robot_xy[r, 1]) - y), lid)
                 for lid, (x, y, _) in leaders.items() if count[lid] < capacity]
        if not rooms:
            continue
        _, best = min(rooms)
        plan[r] = best
        count[best] += 1
    return plan


AVOID_M = 0.5  # a new slot keeps this far from other teams' bodies (they move about their own slots)


def slot_for_newcomer(slots: FloatArray, newcomer: FloatArray, inner_m: float = 0.5,
                      avoid: FloatArray | None = None) -> FloatArray:
    """Where an adopted robot joins a formation (leader frame): the free place nearest to where
    it stands now, so it drives in from its own side. Free: at least MIN_SPACING_M from every
    slot (the safety filter's barrier leaves a settled team alone), between ``inner_m`` and
    PRESET_REACH_M from the leader (where the camera sees it); a 5 cm grid, nearest first,
    ties to the lower grid point: every leader computing it gets the same point. ``avoid``:
    other teams' bodies (leader frame), kept AVOID_M away where there is room (a slot the
    safety filter could never let a robot reach would hold it short for ever)."""
    step = 0.05
    axis = np.arange(-PRESET_REACH_M, PRESET_REACH_M + step / 2, step)
    gx, gy = np.meshgrid(axis, axis)
    grid = np.column_stack([gx.ravel(), gy.ravel()])
    r = np.hypot(grid[:, 0], grid[:, 1])
    ok = (r >= inner_m) & (r <= PRESET_REACH_M)
    if slots.size:
        gap = np.min(np.hypot(grid[:, None, 0] - slots[None, :, 0], grid[:, None, 1] - slots[None, :, 1]), axis=1)
        ok &= gap >= MIN_SPACING_M
    if avoid is not None and len(avoid):
        av = np.asarray(avoid, dtype=np.float64).reshape(-1, 2)
        clear = np.min(np.hypot(grid[:, None, 0] - av[None, :, 0], grid[:, None, 1] - av[None, :, 1]), axis=1)
        if np.any(ok & (clear >= AVOID_M)):
            ok &= clear >= AVOID_M
    free = grid[ok]
    if free.shape[0] == 0:  # no room left in the ring: behind the rearmost slot
        rear = slots[np.argmin(slots[:, 1])] if slots.size else np.zeros(2)
        return np.array([rear[0], rear[1] - MIN_SPACING_M])
    d = np.hypot(free[:, 0] - newcomer[0], free[:, 1] - newcomer[1])
    return np.asarray(free[int(np.argmin(d))], dtype=np.float64)


def closest_distance(state: ArenaState) -> float:
    """The smallest centre-to-centre distance (m) between any two bodies of the arena, robots
    and leaders alike (what the safety filter keeps above its min_distance_m)."""
    xy = np.vstack([state.robots[:, :2], state.leaders[:, :2]])
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    d[np.diag_indices_from(d)] = np.inf
    return float(d.min()) if d.size > 1 else math.inf
