"""World-frame team dynamics: leader and followers as unicycles, integrated exactly.

Followers have a first-order actuator lag, speed and acceleration limits,
wheel-speed noise and scheduled disturbances (e.g. stuck for a while, as
follower 2 in the paper's experiment 2). Each step holds the velocities
constant at their mean over the step and moves along the exact arc, so there
is no Euler drift. Deterministic given the rng passed in. The per-follower
math is one compiled kernel shared with the whole-run simulator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from core.geometry import (
    heading_leader_to_world,
    heading_world_to_leader,
    leader_to_world,
    world_to_leader,
    wrap_angle,
)
from core.jit import kernel
from core.types import BoolArray, Commands, FloatArray, float_rows, numbers_in_field_order


@dataclass(frozen=True)
class FollowerDynamics:
    """How real followers differ from ideal unicycles. Defaults are ideal."""

    actuator_tau_s: float = 0.0  # first-order lag of the velocities to the command
    speed_max_mps: float = math.inf
    turn_max_rps: float = math.inf
    accel_max_mps2: float = math.inf
    turn_accel_max_rps2: float = math.inf
    wheel_noise_mps: float = 0.0  # std of each wheel's speed error, per step
    wheel_base_m: float = 0.12  # distance between the wheels, for the noise model

    def as_array(self) -> FloatArray:
        return numbers_in_field_order(self)


DISTURBANCE_KINDS = ("stuck", "hidden")


@dataclass(frozen=True)
class Disturbance:
    """From start_s until end_s, follower ``follower`` (0-based) cannot move ("stuck") or
    cannot be seen by the leader's camera ("hidden": occluded in the renderer)."""

    follower: int
    start_s: float
    end_s: float
    kind: str = "stuck"


def stuck_mask(disturbances: tuple[Disturbance, ...], n: int, t: ArrayLike) -> BoolArray:
    """(len(t), n) True where a follower is stuck at time t."""
    return disturbance_mask(disturbances, n, t, "stuck")


def disturbance_mask(disturbances: tuple[Disturbance, ...], n: int, t: ArrayLike, kind: str) -> BoolArray:
    """(len(t), n) True where a disturbance of this kind acts on a follower at time t."""
    times = np.atleast_1d(np.asarray(t, dtype=np.float64))
    mask = np.zeros((times.shape[0], n), dtype=np.bool_)
    for d in disturbances:
        if d.kind == kind and 0 <= d.follower < n:
            mask[:, d.follower] |= (times >= d.start_s) & (times < d.end_s)
    return mask


@dataclass(frozen=True)
class TeamState:
    """Ground truth in the world frame."""

    leader: FloatArray  # (3,) x, y, theta
    followers: FloatArray  # (n, 3) x, y, theta
    follower_vel: FloatArray  # (n, 2) actual v, w after lag

    @property
    def n(self) -> int:
        return int(self.followers.shape[0])


def make_team_state(
    p_leader_frame: ArrayLike,
    a_leader_frame: ArrayLike,
    leader_pose: ArrayLike = (0.0, 0.0, np.pi / 2),
) -> TeamState:
    """A resting team from follower poses given in the leader frame (as the paper does)."""
    lp = np.asarray(leader_pose, dtype=np.float64)
    p = np.atleast_2d(np.asarray(p_leader_frame, dtype=np.float64))
    xy = leader_to_world(p, lp[:2], float(lp[2]))
    th = heading_leader_to_world(np.asarray(a_leader_frame, dtype=np.float64), float(lp[2]))
    return TeamState(lp.copy(), np.column_stack([xy, th]), np.zeros((p.shape[0], 2)))


@kernel
def arc_kernel(poses: FloatArray, v: FloatArray, w: FloatArray, dt: float, out: FloatArray) -> None:
    """Exact motion of unicycles (m, 3) with constant (v, w) over dt, into out.

    The chord has length v dt sin(h)/h (h = w dt / 2) and direction theta + h:
    exact, and with no singularity at w = 0.
    """
    for i in range(poses.shape[0]):
        half = 0.5 * w[i] * dt
        sinc = 1.0 - half * half / 6.0 if abs(half) < 1e-4 else math.sin(half) / half
        chord = v[i] * dt * sinc
        mid = poses[i, 2] + half
        out[i, 0] = poses[i, 0] + chord * math.cos(mid)
        out[i, 1] = poses[i, 1] + chord * math.sin(mid)
        out[i, 2] = wrap_angle(poses[i, 2] + 2.0 * half)


def integrate_unicycle(pose: ArrayLike, v: ArrayLike, w: ArrayLike, dt: float) -> FloatArray:
    """Poses (m, 3) after dt at constant (v, w) each: see :func:`arc_kernel`."""
    q = np.ascontiguousarray(np.atleast_2d(np.asarray(pose, dtype=np.float64)))
    m = q.shape[0]
    v_arr = float_rows(v, (m,))
    w_arr = float_rows(w, (m,))
    out = np.empty_like(q)
    arc_kernel(q, v_arr, w_arr, float(dt), out)
    return out


@kernel
def followers_kernel(
    poses: FloatArray,
    vel: FloatArray,
    v_cmd: FloatArray,
    w_cmd: FloatArray,
    dt: float,
    dyn: FloatArray,
    stuck: BoolArray,
    noise: FloatArray,
    out_poses: FloatArray,
    out_vel: FloatArray,
) -> None:
    """One step of n followers under their commands; ``dyn`` is FollowerDynamics.as_array().

    ``noise`` (n, 2) are standard-normal draws for the right and left wheel.
    """
    tau, v_lim, w_lim, acc_v, acc_w, wheel_sigma, base = (
        dyn[0], dyn[1], dyn[2], dyn[3], dyn[4], dyn[5], dyn[6],
    )
    decay = math.exp(-dt / tau) if tau > 0.0 else 0.0
    mean_v = np.empty(poses.shape[0])
    mean_w = np.empty(poses.shape[0])
    for i in range(poses.shape[0]):
        vc = min(max(v_cmd[i], -v_lim), v_lim)
        wc = min(max(w_cmd[i], -w_lim), w_lim)
        v0 = vel[i, 0]
        w0 = vel[i, 1]
        v1 = vc + (v0 - vc) * decay
        w1 = wc + (w0 - wc) * decay
        v1 = min(max(v1, v0 - acc_v * dt), v0 + acc_v * dt)
        w1 = min(max(w1, w0 - acc_w * dt), w0 + acc_w * dt)
        if stuck[i]:
            v1 = 0.0
            w1 = 0.0
            mv = 0.0
            mw = 0.0
        else:
            mv = 0.5 * (v0 + v1) if tau > 0.0 else v1
            mw = 0.5 * (w0 + w1) if tau > 0.0 else w1
            if wheel_sigma > 0.0:
                mv += 0.5 * wheel_sigma * (noise[i, 0] + noise[i, 1])
                mw += wheel_sigma * (noise[i, 0] - noise[i, 1]) / base
        out_vel[i, 0] = v1
        out_vel[i, 1] = w1
        mean_v[i] = mv
        mean_w[i] = mw
    arc_kernel(poses, mean_v, mean_w, dt, out_poses)


def step_team(
    state: TeamState,
    commands: Commands,
    leader_twist: tuple[float, float],
    dt: float,
    t: float,
    rng: np.random.Generator,
    dynamics: FollowerDynamics = FollowerDynamics(),
    disturbances: tuple[Disturbance, ...] = (),
) -> TeamState:
    """Advance the world by dt from time t under the followers' commands and the leader's twist."""
    n = state.n
    noise = rng.standard_normal((n, 2)) if dynamics.wheel_noise_mps > 0.0 else np.zeros((n, 2))
    out_poses = np.empty((n, 3))
    out_vel = np.empty((n, 2))
    followers_kernel(
        np.ascontiguousarray(state.followers),
        np.ascontiguousarray(state.follower_vel),
        np.ascontiguousarray(np.asarray(commands.v, dtype=np.float64)),
        np.ascontiguousarray(np.asarray(commands.w, dtype=np.float64)),
        float(dt),
        dynamics.as_array(),
        stuck_mask(disturbances, n, t)[0],
        noise,
        out_poses,
        out_vel,
    )
    leader = integrate_unicycle(state.leader, leader_twist[0], leader_twist[1], dt)[0]
    return TeamState(leader, out_poses, out_vel)


def measure_followers(
    state: TeamState,
    rng: np.random.Generator,
    position_noise_m: float = 0.0,
    heading_noise_rad: float = 0.0,
) -> tuple[FloatArray, FloatArray]:
    """Leader-frame follower poses, ground truth plus optional Gaussian noise: (n, 2), (n,)."""
    theta = float(state.leader[2])
    p = world_to_leader(state.followers[:, :2], state.leader[:2], theta)
    a = heading_world_to_leader(state.followers[:, 2], theta)
    if position_noise_m > 0.0:
        p = p + rng.normal(0.0, position_noise_m, size=p.shape)
    if heading_noise_rad > 0.0:
        a = wrap_angle(a + rng.normal(0.0, heading_noise_rad, size=a.shape))
    return p, np.asarray(a, dtype=np.float64)
