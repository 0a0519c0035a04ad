"""A goal for the leader: reactive navigation around obstacles on the free-space scan.

The method is the vector field histogram in its VFH+ form (Borenstein & Koren, "The vector
field histogram — fast obstacle avoidance for mobile robots", IEEE T-RA 7(3), 1991; Ulrich &
Borenstein, "VFH+: reliable obstacle avoidance for fast mobile robots", ICRA 1998), which
suits a scan: every obstacle point within the look-ahead blocks, in a polar histogram of the
directions around the leader, the bearings within ±asin(r / d) of its own (d: its distance;
r: the leader's radius grown by the clearance, or the team's half-width at its narrowest
plus a follower's radius and margin, whichever is larger), i.e. the obstacles are enlarged
by the size of what must pass (VFH+'s enlargement) so the leader can be treated as a point. Of the free
bearings the leader takes the one nearest to the goal's, with a small cost for turning away
from the heading it chose last (VFH+'s cost function, which stops it from hesitating between
two gaps).

Speed: the leader slows where obstacles are near ahead, as it turns, near the goal (it stops
within ``arrive_m``), and for its team (``team_error_m``: the followers' largest formation
error — the paper's robots are slow, so a leader that runs away from its team breaks the
formation; this is the simplest coordination the paper's §6 asks for). It never waits
entirely: a follower whose slot lies behind an obstacle (the filter holds it there) is
freed when the leader creeps on and the slot moves past.

The formation may shrink to pass a gap: the free half-width of the corridor the team drives
through (from the obstacle points within it, from behind the last followers to ahead of the
leader) against the formation's half-width gives a lateral scale in [``min_scale``, 1] (the
slots' x only: the team narrows, as people do in a doorway); it is rate-limited so the
followers can follow, and grows back after.

Everything is in the leader frame (x right, y ahead; bearings from ahead, counter-clockwise);
the goal is given there (the caller turns the world goal into it with the leader's odometry,
eq. 38).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.control.safety import SafetySettings
from core.types import FloatArray


@dataclass(frozen=True)
class NavSettings:
    """The navigator's parameters (SI units)."""

    speed_mps: float = 0.08  # cruise speed
    turn_max_rps: float = 0.6
    heading_gain: float = 1.2  # ω = gain · (chosen bearing), clamped
    leader_radius_m: float = 0.25  # the leader's body
    clearance_m: float = 0.12  # kept between its body and an obstacle (the followers have the filter and the scale)
    lookahead_m: float = 1.6  # obstacles further than this do not block a direction
    bin_deg: float = 5.0
    turn_cost: float = 0.3  # per radian away from the last chosen bearing (relative to the goal's cost 1)
    arrive_m: float = 0.05  # the goal is reached within this
    slow_m: float = 0.5  # the leader slows within this of the goal
    team_error_m: float = 0.15  # formation error at which the leader slows to a creep for its team
    creep: float = 0.25  # of the cruise speed: a leader that stopped for a follower stuck behind an
    # obstacle would wait for ever (the follower's slot stays behind it); creeping on moves the slot past
    corridor_m: float = 1.2  # the corridor ahead measured for the formation's scale
    scale_rate: float = 0.08  # per second the formation's scale may change


@dataclass(frozen=True)
class NavOutput:
    twist: tuple[float, float]  # (v, ω) of the leader
    heading: float  # the bearing chosen (rad, leader frame); NaN when stopped
    reached: bool
    blocked: bool  # no free direction: the leader stands still
    scale: float  # the formation's scale this tick


def goal_in_leader_frame(goal_world: tuple[float, float], pose: FloatArray) -> FloatArray:
    """The goal (world, m) in the frame of the leader at ``pose`` (x, y, θ): R(−φ)(g − p), φ = θ − π/2."""
    phi = float(pose[2]) - math.pi / 2
    c, s = math.cos(phi), math.sin(phi)
    dx, dy = goal_world[0] - float(pose[0]), goal_world[1] - float(pose[1])
    return np.array([c * dx + s * dy, -s * dx + c * dy])


def blocked_bins(points: FloatArray, s: NavSettings, radius_m: float) -> tuple[FloatArray, np.ndarray]:
    """(bin bearings (B,), blocked (B,) bool): VFH+'s binary polar histogram, obstacles
    enlarged by ``radius_m``."""
    n_bins = int(round(360.0 / s.bin_deg))
    bearings: FloatArray = -math.pi + (np.arange(n_bins, dtype=np.float64) + 0.5) * (2 * math.pi / n_bins)
    blocked = np.zeros(n_bins, dtype=bool)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts):
        d = np.hypot(pts[:, 0], pts[:, 1])
        near = d <= s.lookahead_m
        r = radius_m
        for dist, b in zip(d[near], np.arctan2(-pts[near, 0], pts[near, 1])):
            half = math.pi / 2 if dist <= r else math.asin(r / dist)
            gap = np.abs((bearings - b + math.pi) % (2 * math.pi) - math.pi)
            blocked |= gap <= half
    return bearings, blocked


ROBOT_RADIUS_M = SafetySettings.follower_radius_m  # a follower's footprint as a disc
MARGIN_M = SafetySettings.obstacle_margin_m  # what the safety filter keeps from an obstacle's surface by default


def formation_scale(points: FloatArray, half_width_m: float, depth_m: float, s: NavSettings, min_scale: float,
                    robot_radius_m: float = ROBOT_RADIUS_M, margin_m: float = MARGIN_M) -> float:
    """The lateral scale the formation needs for the corridor it drives through: its
    half-width against the free half-width beside the leader's path (obstacle points from
    ``depth_m`` behind the leader, where its last followers are, to ``corridor_m`` ahead)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if half_width_m <= 0 or len(pts) == 0:
        return 1.0
    ahead = (pts[:, 1] > -depth_m - robot_radius_m) & (pts[:, 1] < s.corridor_m) \
        & (np.abs(pts[:, 0]) < half_width_m + robot_radius_m + margin_m)
    if not ahead.any():
        return 1.0
    free = float(np.abs(pts[ahead, 0]).min()) - robot_radius_m - margin_m
    return float(np.clip(free / half_width_m, min_scale, 1.0))


def navigate(goal: FloatArray, points: FloatArray, team_error_m: float, last_heading: float, last_scale: float,
             slots: FloatArray, min_scale: float, dt: float, s: NavSettings = NavSettings()) -> NavOutput:
    """One tick of the goal mode: the leader's twist toward ``goal`` (leader frame) around the
    obstacle ``points`` (leader frame), and the lateral scale of the formation's ``slots``."""
    half_width_m = float(np.abs(slots[:, 0]).max()) if len(slots) else 0.0
    depth_m = float(max(0.0, -float(slots[:, 1].min()))) if len(slots) else 0.0
    target = math.hypot(float(goal[0]), float(goal[1]))
    want = math.atan2(-float(goal[0]), float(goal[1]))
    step = s.scale_rate * dt
    scale = float(np.clip(formation_scale(points, half_width_m, depth_m, s, min_scale), last_scale - step,
                        last_scale + step))
    if target <= s.arrive_m:
        return NavOutput((0.0, 0.0), math.nan, True, False, scale)
    # the way must be wide enough for the leader and for its team narrowed as far as it may be
    radius = max(s.leader_radius_m + s.clearance_m, min_scale * half_width_m + ROBOT_RADIUS_M + MARGIN_M)
    bearings, blocked = blocked_bins(points, s, radius)
    if target < s.lookahead_m:  # obstacles beyond the goal do not block the way to it
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        _, blocked = blocked_bins(pts[np.hypot(pts[:, 0], pts[:, 1]) < target + s.leader_radius_m], s, radius)
    if blocked.all():
        return NavOutput((0.0, 0.0), math.nan, False, True, scale)
    wrap = np.abs((bearings - want + math.pi) % (2 * math.pi) - math.pi)
    last = 0.0 if not math.isfinite(last_heading) else last_heading
    turn = np.abs((bearings - last + math.pi) % (2 * math.pi) - math.pi)
    cost = np.where(blocked, np.inf, wrap + s.turn_cost * turn)
    k = int(np.argmin(cost))
    free_goal = not blocked[int(np.argmin(wrap))]
    heading = want if free_goal else float(bearings[k])  # the goal's own bearing when it is free
    w = float(np.clip(s.heading_gain * heading, -s.turn_max_rps, s.turn_max_rps))
    v = s.speed_mps * max(0.0, math.cos(heading)) ** 2  # turn on the spot when the way is behind
    v *= min(1.0, target / s.slow_m) if target < s.slow_m else 1.0
    v *= float(np.clip(1.0 - (team_error_m - s.team_error_m / 2) / s.team_error_m, s.creep, 1.0))
    return NavOutput((max(v, 0.0), w), heading, False, False, scale)
