"""A safety filter on every command: control barrier functions (CBF) that keep robots apart.

The controller's (v, ω) for the whole team go through one quadratic program per tick that
changes them as little as possible while keeping, for every pair of followers, every
follower and the leader, and every follower and each obstacle, a minimum distance. This is
the barrier certificate of Robotarium (Wang, Ames, Egerstedt, "Safety barrier certificates
for collisions-free multirobot systems", IEEE T-RO 33(3), 2017, and the Robotarium's
``create_unicycle_barrier_certificate``): each unicycle is handled through a point a short
distance ``projection_m`` ahead of its axle, whose velocity u = T(a)·(v, ω) is fully
actuated (T(a) = [[cos a, -l sin a], [sin a, l cos a]] is invertible for l > 0), and each
pair's barrier h = ‖qᵢ − qⱼ‖² − (d + 2l)² is kept non-negative by ḣ ≥ −γ·h³ (the points'
distance grown by l per robot, so the centres keep d).

Everything is in the leader frame, where the followers move by ṗ = v(cos a, sin a) − ζ̇_comp(p)
(eq. 26). The compensation ζ̇_comp(p) = (−ω_l y, v_l + ω_l x) is a rigid-body field (see
docs/paper-notes.md), so the difference of two points' compensations is perpendicular to the
line between them and drops out of ḣ for a pair of followers and for a follower and a
world-fixed obstacle; against the leader (fixed at the origin of its own frame) it leaves
the known term −2·y·v_l.

The filter never makes things worse: a solve that fails (infeasible, a solver error, no
solver installed) commands zero to every follower that has a constraint near its limit and
says so; the others keep the controller's commands. A QP solver is called through qpsolvers
(DAQP, a dual active-set solver for small dense QPs: the team's QP has 2n variables and at
most n(n+1)/2 + n·m rows, plus 4n rows for the command limits).

Why DAQP: compared through qpsolvers on the bench's packed teams (``bench_safety_filter``;
median per solve on this 2-core machine, and the largest difference in (v, ω) from DAQP's):
6 followers: DAQP 0.44 ms, proxsuite 0.53 ms (2.5e-5), Clarabel 1.03 ms (9e-8), OSQP 1.39 ms
(0.06: its default tolerances leave constraints slightly violated); 50 followers: Clarabel
4.3 ms, OSQP 5.7 ms, DAQP 3.5–6.0 ms, proxsuite 62 ms. An active-set method returns the
exact vertex, so a barrier at its limit is met exactly, and DAQP is the fastest for the team
sizes the live service drives (up to 8).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal

import numpy as np

from core.bounds import number_default
from core.types import BoolArray, Commands, FloatArray, IntArray

SolveStatus = Literal["inactive", "filtered", "infeasible", "no solver"]


@dataclass(frozen=True)
class SafetySettings:
    """The filter's parameters (SI units)."""

    min_distance_m: float = number_default("safety_distance_m")  # centre to centre, any two robots (core.bounds)
    obstacle_margin_m: float = 0.10  # from a follower's centre to an obstacle's surface, beyond its half-width
    follower_radius_m: float = 0.15  # half the follower's diagonal: what must clear an obstacle's surface
    projection_m: float = 0.025  # the point ahead of the axle the barriers act on
    barrier_gain: float = 100.0  # γ in ḣ ≥ −γ h³ (Robotarium's default)
    activity_m: float = 0.6  # constraints are written only for robots within this of each other
    keep_right_deg: float = 40.0  # a follower the filter stalls aims this far to its right instead (0: never)
    solver: str = "daqp"

    @staticmethod
    def for_distance(min_distance_m: float, **changes: float) -> "SafetySettings":
        """The settings for a minimum distance, constraints written a little further out."""
        return SafetySettings(min_distance_m=min_distance_m, activity_m=max(0.6, min_distance_m + 0.35), **changes)  # type: ignore[arg-type]  # float fields only

    def __post_init__(self) -> None:
        for name in ("min_distance_m", "projection_m", "barrier_gain", "activity_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"safety {name} = {value!r}: must be a positive number")
        if self.activity_m < self.min_distance_m:
            raise ValueError(f"safety activity_m = {self.activity_m}: must be at least min_distance_m ="
                             f" {self.min_distance_m}")


@dataclass(frozen=True)
class SafetyResult:
    commands: Commands  # what the followers are sent
    status: SolveStatus
    changed: FloatArray  # (n,) how much each follower's (v, ω) moved: ‖Δv‖ + l‖Δω‖ (m/s)
    constrained: BoolArray  # (n,) a constraint of this follower was written (it is near something)
    active: BoolArray  # (n,) one of its constraints is at its limit (the filter acts on it)
    min_distance_m: float  # the smallest centre distance between two robots (followers and leader), now
    message: str = ""  # why a solve failed


def _points(p: FloatArray, a: FloatArray, ahead: float) -> FloatArray:
    return p + ahead * np.column_stack([np.cos(a), np.sin(a)])


def _to_point_velocity(a: FloatArray, v: FloatArray, w: FloatArray, ahead: float) -> FloatArray:
    """(n, 2) u = T(a)·(v, ω)."""
    c, s = np.cos(a), np.sin(a)
    return np.column_stack([c * v - ahead * s * w, s * v + ahead * c * w])


def _to_unicycle(a: FloatArray, u: FloatArray, ahead: float) -> tuple[FloatArray, FloatArray]:
    """(v, ω) = T(a)⁻¹·u."""
    c, s = np.cos(a), np.sin(a)
    return c * u[:, 0] + s * u[:, 1], (-s * u[:, 0] + c * u[:, 1]) / ahead


def team_min_distance(p: FloatArray) -> float:
    """Smallest centre distance among the followers (n, 2) and the leader at the origin."""
    pts = np.vstack([np.zeros((1, 2)), np.asarray(p, dtype=np.float64)])
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    d[np.diag_indices_from(d)] = np.inf
    return float(d.min()) if len(pts) > 1 else float("inf")


@functools.lru_cache(maxsize=32)
def _pairs(n: int) -> tuple[IntArray, IntArray]:
    """Every pair i < j of n followers (numpy's triu_indices, made once per team size: the
    filter asks each tick), read-only."""
    i, j = np.triu_indices(n, 1)
    i.flags.writeable = j.flags.writeable = False
    return i, j


def barrier_constraints(
    p: FloatArray, a: FloatArray, leader_twist: tuple[float, float], obstacles: FloatArray, s: SafetySettings,
    known: BoolArray | None = None,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """The rows G u ≤ h on the point velocities u (2n,) and, per follower, whether it has one.

    ``obstacles``: (m, 3) centre x, y and radius (m) in the leader frame; ``known``: followers
    whose pose is known (the others get no constraint: they are commanded zero anyway)."""
    n = p.shape[0]
    known = np.ones(n, dtype=bool) if known is None else np.asarray(known, dtype=bool)
    q = _points(p, a, s.projection_m)
    # on the points l ahead, distances grown by l per robot: the centres then keep the distance asked for
    ahead = s.projection_m
    d2, d2_leader, reach2 = (s.min_distance_m + 2 * ahead) ** 2, (s.min_distance_m + ahead) ** 2, s.activity_m ** 2
    blocks: list[tuple[FloatArray, FloatArray]] = []  # (rows (k, 2n), right-hand sides (k,))
    # every pair of known followers within reach: -2e·uᵢ + 2e·uⱼ ≤ γh³
    i, j = _pairs(n)
    e = q[i] - q[j]
    near = known[i] & known[j] & (np.einsum("kd,kd->k", e, e) <= reach2)
    i, j, e = i[near], j[near], e[near]
    rows = np.zeros((len(i), n, 2))
    rows[np.arange(len(i)), i] = -2.0 * e
    rows[np.arange(len(i)), j] = 2.0 * e
    blocks.append((rows.reshape(len(i), 2 * n), s.barrier_gain * (np.einsum("kd,kd->k", e, e) - d2) ** 3))
    constrained = np.zeros(n, dtype=bool)
    constrained[i] = constrained[j] = True
    # the leader's body, fixed at the origin of its frame: -2q·u ≤ γh³ − 2·y·v_l
    k = np.nonzero(known & (np.einsum("kd,kd->k", q, q) <= reach2))[0]
    rows = np.zeros((len(k), n, 2))
    rows[np.arange(len(k)), k] = -2.0 * q[k]
    blocks.append((rows.reshape(len(k), 2 * n),
                   s.barrier_gain * (np.einsum("kd,kd->k", q[k], q[k]) - d2_leader) ** 3 - 2.0 * q[k, 1] * leader_twist[0]))
    constrained[k] = True
    # obstacles (world-fixed): -2(q − o)·u ≤ γh³
    obs = np.asarray(obstacles, dtype=np.float64).reshape(-1, 3)
    if len(obs):
        fi = np.repeat(np.arange(n), len(obs))  # every (follower, obstacle) pair
        oi = np.tile(np.arange(len(obs)), n)
        e = q[fi] - obs[oi, :2]
        radius = obs[oi, 2] + s.obstacle_margin_m + s.follower_radius_m + ahead
        near = known[fi] & (np.linalg.norm(e, axis=1) - radius <= s.activity_m)
        fi, e, radius = fi[near], e[near], radius[near]
        rows = np.zeros((len(fi), n, 2))
        rows[np.arange(len(fi)), fi] = -2.0 * e
        blocks.append((rows.reshape(len(fi), 2 * n), s.barrier_gain * (np.einsum("kd,kd->k", e, e) - radius ** 2) ** 3))
        constrained[fi] = True
    return np.vstack([b[0] for b in blocks]), np.concatenate([b[1] for b in blocks]), constrained


def obstacle_rows(points: FloatArray, robots: FloatArray, settings: SafetySettings, sectors: int = 8) -> FloatArray:
    """The obstacles as the filter takes them, (k, 3) x, y, radius 0: of the obstacle
    ``points`` the leader knows (leader frame; the free-space scan's, or the truth's), for
    each robot within reach the nearest one in each of ``sectors`` directions around it —
    a handful of rows per robot instead of hundreds."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    rob = np.asarray(robots, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0 or len(rob) == 0:
        return np.zeros((0, 3))
    reach = settings.activity_m + settings.obstacle_margin_m + settings.follower_radius_m
    d = pts[None, :, :] - rob[:, None, :]
    dist = np.hypot(d[..., 0], d[..., 1])
    sector = np.floor((np.arctan2(d[..., 1], d[..., 0]) + np.pi) / (2 * np.pi / sectors)).astype(np.int64) % sectors
    chosen: set[int] = set()
    for i in range(len(rob)):
        near = np.nonzero(dist[i] <= reach)[0]
        best: dict[int, int] = {}
        for k in near[np.argsort(dist[i, near])]:
            best.setdefault(int(sector[i, k]), int(k))
        chosen.update(best.values())
    picked = pts[sorted(chosen)] if chosen else np.zeros((0, 2))
    return np.column_stack([picked, np.zeros(len(picked))])


def _limit_rows(a: FloatArray, ahead: float, v_max: float, w_max: float) -> tuple[FloatArray, FloatArray]:
    """|v| ≤ v_max and |ω| ≤ ω_max as rows on u: v = c·uₓ + s·u_y, ω = (−s·uₓ + c·u_y)/l."""
    n = a.shape[0]
    G = np.zeros((4 * n, 2 * n))
    h = np.zeros(4 * n)
    for i, ai in enumerate(a):
        c, s = np.cos(ai), np.sin(ai)
        for k, (row, bound) in enumerate((((c, s), v_max), ((-c, -s), v_max),
                                          ((-s / ahead, c / ahead), w_max), ((s / ahead, -c / ahead), w_max))):
            G[4 * i + k, 2 * i:2 * i + 2] = row
            h[4 * i + k] = bound
    return G, h


def _solve(u_nom: FloatArray, G: FloatArray, h: FloatArray, solver: str) -> tuple[FloatArray | None, SolveStatus, str]:
    """min ½‖u − u_nom‖² s.t. G u ≤ h through qpsolvers: (u or None, status, why it failed)."""
    try:
        import qpsolvers
    except ImportError:
        return None, "no solver", "qpsolvers is not installed"
    try:
        u = qpsolvers.solve_qp(P=np.eye(u_nom.shape[0]), q=-u_nom, G=G, h=h, solver=solver)
    except qpsolvers.SolverNotFound:
        return None, "no solver", f"the QP solver {solver!r} is not installed"
    except Exception as exc:  # noqa: BLE001 - a failing solver must stop the robots, not the loop
        return None, "infeasible", f"the {solver} solver failed: {type(exc).__name__}: {exc}"[:200]
    if u is None:
        return None, "infeasible", "the barrier QP has no solution"
    return np.asarray(u, dtype=np.float64), "filtered", ""


def load_solver(solver: str) -> SolveStatus:
    """Import the QP library and ``solver`` now, by solving a two-variable QP whose one constraint
    binds: the first solve imports them (20-50 ms of a tick, measured in the live loop), so the
    loop's warm-up calls this before its clock starts (app.live.warmup). The solve's status."""
    _, status, _ = _solve(np.zeros(2), np.array([[1.0, 0.0]]), np.array([-1.0]), solver)
    return status


def filter_commands(
    p: FloatArray, a: FloatArray, commands: Commands, leader_twist: tuple[float, float],
    obstacles: FloatArray | None = None, settings: SafetySettings = SafetySettings(),
    known: BoolArray | None = None, limits: tuple[float, float] | None = None,
) -> SafetyResult:
    """The commands nearest to the controller's that keep every barrier (see the module docstring).

    p (n, 2) m and a (n,) rad: followers in the leader frame; ``known``: whose pose is known
    (default all; the others keep their commands and get no constraint); commands: the
    controller's (v, ω); leader_twist: (v_l, ω_l); obstacles (m, 3): x, y, radius in the leader
    frame; ``limits``: (v_max, ω_max) the filtered commands must keep too."""
    p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
    a = np.asarray(a, dtype=np.float64).reshape(-1)
    n = p.shape[0]
    known = np.ones(n, dtype=bool) if known is None else np.asarray(known, dtype=bool) & np.isfinite(p).all(axis=1)
    v0 = np.asarray(commands.v, dtype=np.float64)
    w0 = np.asarray(commands.w, dtype=np.float64)
    obstacles = np.zeros((0, 3)) if obstacles is None else np.asarray(obstacles, dtype=np.float64).reshape(-1, 3)
    ahead = settings.projection_m
    G, h, constrained = barrier_constraints(p, a, leader_twist, obstacles, settings, known)
    nearest = team_min_distance(p[known])
    none = np.zeros(n, dtype=bool)
    if G.shape[0] == 0:
        return SafetyResult(commands, "inactive", np.zeros(n), none, none, nearest)
    u_nom = _to_point_velocity(a, v0, w0, ahead).reshape(-1)
    if np.all(G @ u_nom <= h):  # the controller's commands already keep every barrier
        return SafetyResult(commands, "inactive", np.zeros(n), constrained, none, nearest)
    G_all, h_all = G, h
    if limits is not None:
        G_lim, h_lim = _limit_rows(a, ahead, *limits)
        G_all, h_all = np.vstack([G, G_lim]), np.concatenate([h, h_lim])
    u, status, message = _solve(u_nom, G_all, h_all, settings.solver)
    if u is not None and settings.keep_right_deg > 0:
        # a barrier stalls two followers that meet head on, or one whose slot lies behind
        # another (the QP's answer is symmetric: nobody moves); each stalled follower then
        # aims to its right by keep_right_deg, as people do in a corridor, and the QP is solved
        # again from there: the symmetry is broken the same way for all, so they pass
        un, uf = u_nom.reshape(n, 2), np.asarray(u).reshape(n, 2)
        speed = np.hypot(un[:, 0], un[:, 1])
        n_pairs = int(np.count_nonzero(np.any(G.reshape(len(h), n, 2) != 0.0, axis=2).sum(axis=1) == 2))
        pair_rows = G[:n_pairs][(h[:n_pairs] - G[:n_pairs] @ u) < 1e-6 * np.maximum(1.0, np.abs(h[:n_pairs]))]
        blocked_by_peer = np.any(pair_rows.reshape(-1, n, 2) != 0.0, axis=(0, 2)) if len(pair_rows) else np.zeros(n, bool)
        # only between followers: one the leader bears down on must back away, not turn aside
        stalled = blocked_by_peer & (speed > 1e-3) & (np.hypot(uf[:, 0], uf[:, 1]) < 0.3 * speed)
        if stalled.any():
            turn = -np.radians(settings.keep_right_deg)
            c, si = np.cos(turn), np.sin(turn)
            aimed = un.copy()
            aimed[stalled] = np.column_stack([c * un[stalled, 0] - si * un[stalled, 1],
                                              si * un[stalled, 0] + c * un[stalled, 1]])
            u2, _, _ = _solve(aimed.reshape(-1), G_all, h_all, settings.solver)
            if u2 is not None and np.all(np.isfinite(u2)):
                u = u2
    if u is None or not np.all(np.isfinite(u)):
        stop = constrained
        v = np.where(stop, 0.0, v0)
        w = np.where(stop, 0.0, w0)
        return SafetyResult(Commands(v, w), status, np.abs(v - v0) + ahead * np.abs(w - w0), constrained, stop, nearest,
                            message or "the barrier QP has no solution")
    v, w = _to_unicycle(a, np.asarray(u).reshape(n, 2), ahead)
    slack = h - G @ u
    active = np.zeros(n, dtype=bool)
    for row in np.nonzero(slack < 1e-6 * np.maximum(1.0, np.abs(h)))[0]:
        active |= np.any(G[row].reshape(n, 2) != 0.0, axis=1)
    return SafetyResult(Commands(v, w), "filtered", np.abs(v - v0) + ahead * np.abs(w - w0), constrained, active, nearest)
