import math

import numpy as np
from numpy.testing import assert_allclose

from core.sim.profiles import ConstantProfile, Eq39Profile, Segment, SegmentsProfile
from core.sim.team import (
    Disturbance,
    FollowerDynamics,
    integrate_unicycle,
    make_team_state,
    measure_followers,
    step_team,
)
from core.types import Commands


def test_arc_integration_is_exact_on_a_circle():
    # v = 0.1, w = 0.5 for 2 pi / w: back to the start, whatever the step count.
    pose = np.array([[1.0, 2.0, 0.3]])
    v, w = 0.1, 0.5
    steps = 7
    dt = 2 * math.pi / w / steps
    for _ in range(steps):
        pose = integrate_unicycle(pose, v, w, dt)
    assert_allclose(pose[0, :2], [1.0, 2.0], atol=1e-12)
    # Quarter circle from the origin facing +x, turning left: ends at (r, r) facing +y.
    r = v / w
    q = integrate_unicycle([[0.0, 0.0, 0.0]], v, w, (math.pi / 2) / w)[0]
    assert_allclose(q, [r, r, math.pi / 2], atol=1e-12)


def test_straight_line_has_no_singularity():
    q = integrate_unicycle([[0.0, 0.0, 0.0]], 0.2, 0.0, 1.5)[0]
    assert_allclose(q, [0.3, 0.0, 0.0], atol=1e-15)


def test_first_order_lag_reaches_63_percent_after_tau():
    dyn = FollowerDynamics(actuator_tau_s=0.3)
    s = make_team_state([[0.0, 0.0]], [math.pi / 2])
    rng = np.random.default_rng(0)
    dt = 0.01
    for k in range(30):
        s = step_team(s, Commands(np.array([0.2]), np.array([0.0])), (0.0, 0.0), dt, k * dt, rng, dyn)
    assert_allclose(s.follower_vel[0, 0], 0.2 * (1 - math.exp(-1.0)), rtol=1e-9)


def test_speed_and_acceleration_limits():
    dyn = FollowerDynamics(speed_max_mps=0.1, accel_max_mps2=1.0)
    s = make_team_state([[0.0, 0.0]], [math.pi / 2])
    s1 = step_team(s, Commands(np.array([5.0]), np.array([0.0])), (0.0, 0.0), 0.01, 0.0,
                   np.random.default_rng(0), dyn)
    assert_allclose(s1.follower_vel[0, 0], 0.01)
    for _ in range(50):
        s1 = step_team(s1, Commands(np.array([5.0]), np.array([0.0])), (0.0, 0.0), 0.01, 0.0,
                       np.random.default_rng(0), dyn)
    assert_allclose(s1.follower_vel[0, 0], 0.1)


def test_stuck_follower_does_not_move_during_its_window_only():
    dist = (Disturbance(1, 1.0, 2.0),)
    s = make_team_state([[0.0, 0.0], [1.0, 0.0]], [math.pi / 2] * 2)
    rng = np.random.default_rng(0)
    cmd = Commands(np.array([0.1, 0.1]), np.array([0.0, 0.0]))
    s_in = step_team(s, cmd, (0.0, 0.0), 0.1, 1.5, rng, disturbances=dist)
    assert_allclose(s_in.followers[1], s.followers[1])
    assert s_in.followers[0, 1] > 0
    s_out = step_team(s, cmd, (0.0, 0.0), 0.1, 2.0, rng, disturbances=dist)
    assert s_out.followers[1, 1] > 0


def test_wheel_noise_is_deterministic_given_the_seed():
    dyn = FollowerDynamics(wheel_noise_mps=0.01)
    s = make_team_state([[0.0, 0.0]], [0.0])
    cmd = Commands(np.array([0.1]), np.array([0.0]))
    a = step_team(s, cmd, (0.0, 0.0), 0.1, 0.0, np.random.default_rng(5), dyn)
    b = step_team(s, cmd, (0.0, 0.0), 0.1, 0.0, np.random.default_rng(5), dyn)
    c = step_team(s, cmd, (0.0, 0.0), 0.1, 0.0, np.random.default_rng(6), dyn)
    assert_allclose(a.followers, b.followers)
    assert not np.allclose(a.followers, c.followers)


def test_measurements_are_in_the_leader_frame():
    s = make_team_state([[0.3, -0.9]], [math.radians(120)], leader_pose=(2.0, -1.0, 0.4))
    p, a = measure_followers(s, np.random.default_rng(0))
    assert_allclose(p, [[0.3, -0.9]], atol=1e-12)
    assert_allclose(a, [math.radians(120)], atol=1e-12)


def test_profiles():
    assert ConstantProfile(0.06, 0.1).twist(5.0) == (0.06, 0.1)
    eq39 = Eq39Profile()
    assert eq39.twist(5.0) == (0.06, 0.0)
    assert_allclose(eq39.twist(10.0)[1], math.radians(1.5) * math.tanh(0.2 * 45), rtol=1e-12)
    assert_allclose(eq39.twist(55.0)[1], 0.0, atol=1e-15)
    assert eq39.twist(99.0)[1] < 0  # ends turning clockwise (docs/paper-notes.md)
    t = np.linspace(0, 120, 241)
    assert_allclose(eq39.twists(t)[:, 1], [eq39.twist(x)[1] for x in t])
    seg = SegmentsProfile((Segment(1.0, 0.1, 0.0), Segment(3.0, 0.05, 0.2)))
    assert seg.twist(0.5) == (0.0, 0.0)
    assert seg.twist(1.0) == (0.1, 0.0)
    assert seg.twist(10.0) == (0.05, 0.2)
