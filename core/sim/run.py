"""Whole-run closed-loop simulation with ground-truth feedback (paper §4).

Per step: measure the followers in the leader frame (plus optional noise) ->
controller (eq. 3-12) -> follower dynamics -> leader moves. The loop runs in
one compiled kernel that calls the same controller and dynamics kernels as
the per-tick API, so the paper's 120 s simulation at 100 Hz takes
milliseconds. Random draws come from the Generator seeded by the scenario.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.config import Scenario
from core.control.assignment import assign_slots
from core.control.formation import controller_kernel, lyapunov
from core.geometry import world_to_leader_kernel, wrap_angle
from core.jit import kernel
from core.sim.team import arc_kernel, followers_kernel, make_team_state, stuck_mask
from core.types import FloatArray, IntArray


@dataclass(frozen=True)
class SimulationLog:
    """Every tick of a run, T rows; followers in the leader frame unless named _world."""

    scenario: Scenario
    t: FloatArray  # (T,) s
    leader: FloatArray  # (T, 3) world x, y, theta
    leader_twist: FloatArray  # (T, 2) v, w
    followers_world: FloatArray  # (T, n, 3)
    p: FloatArray  # (T, n, 2) true positions, leader frame
    a: FloatArray  # (T, n) true headings, leader frame
    p_meas: FloatArray  # (T, n, 2) what the controller was fed
    a_meas: FloatArray  # (T, n)
    p_d: FloatArray  # (T, n, 2) desired positions
    commands: FloatArray  # (T, n, 2) v, w sent
    a_err: FloatArray  # (T, n) heading error a~
    assignment: IntArray  # (n,) slot of each follower

    @property
    def n(self) -> int:
        return int(self.p.shape[1])

    @property
    def error(self) -> FloatArray:
        """(T, n, 2) position error rho~ = rho_d - rho (true), m."""
        return self.p_d - self.p

    @property
    def v_lyap(self) -> FloatArray:
        """(T, n) eq. 21 on the true positions."""
        return lyapunov(self.p, self.p_d)


@kernel
def _run_kernel(
    leader0: FloatArray,
    followers0: FloatArray,
    p_d: FloatArray,
    twists: FloatArray,
    g: FloatArray,
    dyn: FloatArray,
    stuck: np.ndarray,
    wheel_noise: FloatArray,
    meas_noise: FloatArray,
    dt: float,
    out_leader: FloatArray,
    out_followers: FloatArray,
    out_p: FloatArray,
    out_a: FloatArray,
    out_p_meas: FloatArray,
    out_a_meas: FloatArray,
    out_cmd: FloatArray,
    out_a_err: FloatArray,
) -> None:
    steps = twists.shape[0]
    n = followers0.shape[0]
    leader = leader0.copy().reshape(1, 3)
    leader_next = np.empty((1, 3))
    followers = followers0.copy()
    followers_next = np.empty((n, 3))
    vel = np.zeros((n, 2))
    vel_next = np.empty((n, 2))
    state = np.zeros((n, 5))
    ctrl = np.empty((n, 8))
    p_true = np.empty((n, 2))
    p_meas = np.empty((n, 2))
    a_meas = np.empty(n)
    zeros = np.zeros((n, 2))
    active = np.ones(n, dtype=np.bool_)
    one_v = np.empty(1)
    one_w = np.empty(1)
    for k in range(steps):
        theta = leader[0, 2]
        world_to_leader_kernel(followers[:, :2], leader[0, 0], leader[0, 1], theta, p_true)
        for i in range(n):
            a_true = wrap_angle(followers[i, 2] - (theta - 0.5 * math.pi))
            out_a[k, i] = a_true
            p_meas[i, 0] = p_true[i, 0] + meas_noise[k, i, 0]
            p_meas[i, 1] = p_true[i, 1] + meas_noise[k, i, 1]
            a_meas[i] = wrap_angle(a_true + meas_noise[k, i, 2])
        v_l = twists[k, 0]
        w_l = twists[k, 1]
        controller_kernel(p_meas, a_meas, p_d, zeros, v_l, w_l, g, dt, active, state, ctrl)
        out_leader[k] = leader[0]
        out_followers[k] = followers
        out_p[k] = p_true
        out_p_meas[k] = p_meas
        out_a_meas[k] = a_meas
        out_cmd[k, :, 0] = ctrl[:, 0]
        out_cmd[k, :, 1] = ctrl[:, 1]
        out_a_err[k] = ctrl[:, 5]
        followers_kernel(
            followers, vel, ctrl[:, 0].copy(), ctrl[:, 1].copy(), dt, dyn, stuck[k], wheel_noise[k],
            followers_next, vel_next,
        )
        followers[:] = followers_next
        vel[:] = vel_next
        one_v[0] = v_l
        one_w[0] = w_l
        arc_kernel(leader, one_v, one_w, dt, leader_next)
        leader[:] = leader_next


def simulate(scenario: Scenario) -> SimulationLog:
    """Run a scenario with ground-truth (optionally noisy) feedback; deterministic given its seed."""
    dt = 1.0 / scenario.rate_hz
    steps = int(round(scenario.duration_s * scenario.rate_hz)) + 1
    t = np.arange(steps, dtype=np.float64) * dt
    n = scenario.n
    rng = np.random.default_rng(scenario.seed)
    team = make_team_state(scenario.initial_p, scenario.initial_a)
    assignment = assign_slots(scenario.initial_p, scenario.slots)  # eq. 33, once at the start
    p_d = np.ascontiguousarray(scenario.slots[assignment])

    wheel_noise = (
        rng.standard_normal((steps, n, 2))
        if scenario.dynamics.wheel_noise_mps > 0.0
        else np.zeros((steps, n, 2))
    )
    meas = scenario.measurement
    meas_noise = np.zeros((steps, n, 3))
    if meas.position_noise_m > 0.0:
        meas_noise[:, :, :2] = rng.normal(0.0, meas.position_noise_m, (steps, n, 2))
    if meas.heading_noise_rad > 0.0:
        meas_noise[:, :, 2] = rng.normal(0.0, meas.heading_noise_rad, (steps, n))

    twists = np.ascontiguousarray(scenario.leader.twists(t))
    out_leader = np.empty((steps, 3))
    out_followers = np.empty((steps, n, 3))
    out_p = np.empty((steps, n, 2))
    out_a = np.empty((steps, n))
    out_p_meas = np.empty((steps, n, 2))
    out_a_meas = np.empty((steps, n))
    out_cmd = np.empty((steps, n, 2))
    out_a_err = np.empty((steps, n))
    _run_kernel(
        team.leader, team.followers, p_d, twists, scenario.gains.as_array(),
        scenario.dynamics.as_array(), stuck_mask(scenario.disturbances, n, t), wheel_noise,
        meas_noise, dt, out_leader, out_followers, out_p, out_a, out_p_meas, out_a_meas,
        out_cmd, out_a_err,
    )
    return SimulationLog(
        scenario=scenario,
        t=t,
        leader=out_leader,
        leader_twist=twists,
        followers_world=out_followers,
        p=out_p,
        a=out_a,
        p_meas=out_p_meas,
        a_meas=out_a_meas,
        p_d=np.broadcast_to(p_d, (steps, n, 2)).copy(),
        commands=out_cmd,
        a_err=out_a_err,
        assignment=assignment,
    )
