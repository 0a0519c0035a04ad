import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from core.geometry import (
    heading_leader_to_world,
    heading_world_to_leader,
    leader_displacement,
    leader_to_world,
    reexpress_in_new_frame,
    rotate_heading_into_new_frame,
    world_to_leader,
    wrap_angle,
    wrap_scalar,
)
from core.sim.team import integrate_unicycle

finite = st.floats(-1e4, 1e4, allow_nan=False)


@given(finite)
def test_wrap_angle_lands_in_half_open_interval_and_keeps_the_direction(x):
    w = float(wrap_angle(x))
    assert -math.pi < w <= math.pi
    assert math.isclose(math.cos(w), math.cos(x), abs_tol=1e-9)
    assert math.isclose(math.sin(w), math.sin(x), abs_tol=1e-9)


def test_the_scalar_wrap_is_the_ufunc_number_for_number():
    x = np.concatenate([np.random.default_rng(3).uniform(-50, 50, 2000),
                        [math.pi, -math.pi, 3 * math.pi, 0.0, -0.0, 2 * math.pi, 1e-300]])
    assert np.array_equal(wrap_angle(x), [wrap_scalar(float(v)) for v in x])


def test_wrap_angle_maps_both_ends_to_plus_pi():
    assert_allclose(wrap_angle(np.array([math.pi, -math.pi, 3 * math.pi])), [math.pi] * 3, atol=1e-12)


def test_leader_frame_when_leader_faces_north_is_the_world_frame():
    p = np.array([[0.3, -0.9], [-1.0, 2.0]])
    assert_allclose(world_to_leader(p, (0, 0), math.pi / 2), p, atol=1e-12)
    assert_allclose(heading_world_to_leader(np.radians([90.0]), math.pi / 2), np.radians([90.0]))


def test_leader_frame_axes_x_right_y_forward():
    # Leader at (1, 1) facing east: a point 1 m east of it is straight ahead (+y),
    # a point 1 m south is on its right (+x).
    q = world_to_leader([[2.0, 1.0], [1.0, 0.0]], (1.0, 1.0), 0.0)
    assert_allclose(q, [[0.0, 1.0], [1.0, 0.0]], atol=1e-12)
    # A follower heading east like the leader is aligned: a = 90 deg.
    assert_allclose(heading_world_to_leader(0.0, 0.0), math.pi / 2)


@given(finite, finite, st.floats(-10, 10), st.floats(-10, 10), st.floats(-math.pi, math.pi))
def test_world_leader_round_trip(x, y, lx, ly, th):
    p = np.array([[x, y]]) / 100.0
    assert_allclose(leader_to_world(world_to_leader(p, (lx, ly), th), (lx, ly), th), p, atol=1e-9)
    a = float(heading_world_to_leader(heading_leader_to_world(0.7, th), th))
    assert math.isclose(a, 0.7, abs_tol=1e-9)


def test_eq38_reexpression_matches_the_simulated_leader_motion():
    # The leader drives an arc (v, w > 0, CCW); a world-fixed point seen before and
    # after must match reexpress_in_new_frame with the odometry (dx, dy, gamma).
    leader0 = np.array([0.3, -0.2, 1.1])
    leader1 = integrate_unicycle(leader0, 0.06, math.radians(20.0), 1.5)[0]
    point_world = np.array([[0.8, 1.4], [-0.5, 0.2]])
    old = world_to_leader(point_world, leader0[:2], leader0[2])
    new = world_to_leader(point_world, leader1[:2], leader1[2])
    dx, dy, gamma = leader_displacement(leader0, leader1)
    assert gamma > 0
    assert_allclose(reexpress_in_new_frame(old, dx, dy, gamma), new, atol=1e-12)
    # The paper's printed R(+gamma) would be wrong for a CCW turn:
    c, s = math.cos(gamma), math.sin(gamma)
    printed = (np.array([[c, -s], [s, c]]) @ (old - [dx, dy]).T).T
    assert np.abs(printed - new).max() > 1e-3
    # Headings: a1 = alpha0 - gamma.
    heading_world = 0.4
    a0 = heading_world_to_leader(heading_world, leader0[2])
    a1 = heading_world_to_leader(heading_world, leader1[2])
    assert_allclose(rotate_heading_into_new_frame(a0, gamma), a1, atol=1e-12)
