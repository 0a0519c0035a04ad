import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from core.control.formation import (
    ControllerState,
    compensation_velocity,
    compensation_velocity_paper,
    compute_commands,
    heading_saturation,
    lyapunov,
    pose_control,
    saturate_position_error,
)
from core.types import Gains

err = st.floats(-100.0, 100.0, allow_nan=False)
positive = st.floats(1e-3, 1.0)


def test_eq4_hand_values():
    # e = 0.5: (0.1 + 0.05 tanh 0.5) / (0.1 + 0.5) * 0.5
    expected = (0.1 + 0.05 * math.tanh(0.5)) / 0.6 * 0.5
    assert_allclose(saturate_position_error(0.5, 0.1, 0.05, 0.1), expected, rtol=1e-12)
    assert_allclose(saturate_position_error(-0.5, 0.1, 0.05, 0.1), -expected, rtol=1e-12)
    # small-error gain k_f1 / a
    assert_allclose(saturate_position_error(1e-6, 0.1, 0.05, 0.1), 1e-6 * 0.1 / 0.1, rtol=1e-4)


@given(err, positive, st.floats(0.0, 1.0), positive)
def test_eq4_is_bounded_by_the_saturation_value(e, k1, k2, a):
    f = float(saturate_position_error(e, k1, k2, a))
    assert abs(f) < k1 + k2
    assert f * e >= 0.0


def test_eq4_saturates_each_component_separately():
    g = Gains()
    out = pose_control([[0.0, 0.0]], [[10.0, 0.01]], [[0.0, 0.0]], g)[0]
    assert_allclose(out[0], saturate_position_error(10.0, g.k_f1, g.k_f2, g.a))
    assert_allclose(out[1], saturate_position_error(0.01, g.k_f1, g.k_f2, g.a))


def test_eq3_adds_the_desired_velocity():
    g = Gains()
    out = pose_control([[0.2, 0.3]], [[0.2, 0.3]], [[0.05, -0.02]], g)
    assert_allclose(out, [[0.05, -0.02]])


def test_eq12_hand_values():
    assert_allclose(heading_saturation(0.3, 0.5, 1.0), 0.5 * math.tanh(0.3) ** 3, rtol=1e-12)


@given(st.floats(-10.0, 10.0), st.floats(1e-3, 5.0), st.floats(1e-3, 20.0))
def test_eq12_is_odd_and_bounded(e, k1, k2):
    f = float(heading_saturation(e, k1, k2))
    assert abs(f) <= k1
    assert_allclose(float(heading_saturation(-e, k1, k2)), -f, atol=1e-15)
    assert f * e >= 0.0


def test_compensation_with_no_turn_is_the_leader_speed():
    assert_allclose(compensation_velocity([[0.5, -0.3], [-1.0, 2.0]], 0.06, 0.0), [[0.0, 0.06]] * 2)


@given(
    st.floats(0.01, 0.3),  # v_l
    st.floats(math.radians(0.2), math.radians(30.0)),  # w_l > 0
    st.floats(-2.0, 2.0),
    st.floats(-2.0, 2.0),
)
def test_compensation_equals_eq7_to_9_where_they_are_valid(v, w, x, y):
    r = v / w
    if r + x <= 1e-3:
        return  # outside the literal equations' domain (see below)
    assert_allclose(
        compensation_velocity([[x, y]], v, w), compensation_velocity_paper([[x, y]], v, w), atol=1e-12
    )


def test_literal_eq7_to_9_fail_where_documented():
    v, w = 0.06, math.radians(1.5)
    p = [[0.5, 0.7]]
    # w_l < 0: the literal form points the opposite way (r < 0 flips v_i = w_l r_i's
    # sign and arctan's branch together): 0.15 m/s off at (-0.5, -0.3), docs/paper-notes.md.
    for q in ([[0.5, 0.7]], [[-0.5, -0.3]], [[0.0, -0.7]]):
        assert_allclose(compensation_velocity_paper(q, v, -w), -compensation_velocity(q, v, -w), atol=1e-12)
    assert np.abs(compensation_velocity_paper([[-0.5, -0.3]], v, -w)
                  - compensation_velocity([[-0.5, -0.3]], v, -w)).max() > 0.14
    # w_l = 0: r = inf, the literal form is not a number; the rigid form is (0, v).
    with np.errstate(all="ignore"):
        assert not np.all(np.isfinite(compensation_velocity_paper(p, v, 0.0)))
    # r + x < 0 (follower beyond the turn centre): arctan picks the wrong branch.
    far = [[-3.0, 0.5]]
    assert np.abs(compensation_velocity_paper(far, v, w) - compensation_velocity(far, v, w)).max() > 1e-3


def test_commands_hand_computed_for_one_follower():
    # Follower exactly at its slot, aligned, leader straight: v = v_l, w = 0.
    g = Gains()
    out = compute_commands([[0.5, -0.3]], [math.pi / 2], [[0.5, -0.3]], [[0, 0]], 0.06, 0.0, g,
                           ControllerState(np.array([[math.pi / 2, 0, 1, 0.06, 0]])), 0.01)
    assert_allclose(out.commands.v, [0.06], atol=1e-12)
    assert_allclose(out.commands.w, [0.0], atol=1e-12)
    # Turning leader: the follower at (x, y) must do v = |(-w y, v + w x)|, w = w_l.
    w_l = 0.02
    zeta = np.array([0.3 * w_l, 0.06 + 0.5 * w_l])
    a_r = math.atan2(zeta[1], zeta[0])
    state = ControllerState(np.array([[a_r, 0, 1, np.hypot(*zeta), w_l]]))
    out = compute_commands([[0.5, -0.3]], [a_r], [[0.5, -0.3]], [[0, 0]], 0.06, w_l, g, state, 0.01)
    assert_allclose(out.commands.v, [np.hypot(*zeta)], atol=1e-12)
    assert_allclose(out.commands.w, [w_l], atol=1e-12)


def test_eq10_eq11_with_a_heading_error():
    g = Gains(tau_ar=0.0, accel_v_max=20.0, accel_w_max=100.0, w_max=10.0)
    p, p_d = np.array([[0.0, 0.0]]), np.array([[0.2, 0.1]])
    zeta = pose_control(p, p_d, [[0, 0]], g)[0] + [0.0, 0.06]
    a_r = math.atan2(zeta[1], zeta[0])
    a = a_r - 0.4
    prev_a_r = a_r - 0.01
    state = ControllerState(np.array([[prev_a_r, 0.0, 1.0, 0.0, 0.0]]))
    out = compute_commands(p, [a], p_d, [[0, 0]], 0.06, 0.0, g, state, 0.1)
    assert_allclose(out.commands.v, [np.hypot(*zeta) * math.cos(0.4)], rtol=1e-9)
    expected_w = 0.01 / 0.1 + g.k_w1 * math.tanh(g.k_w2 * 0.4) ** 3
    assert_allclose(out.commands.w, [expected_w], rtol=1e-9)
    assert_allclose(out.a_err, [0.4], atol=1e-12)


def test_reference_rate_uses_the_wrapped_difference():
    g = Gains(tau_ar=0.0, w_max=10.0, accel_w_max=100.0)
    # a_r just past +pi from a previous value just below -pi... wrapped change is small.
    p, p_d = np.array([[0.0, 0.0]]), np.array([[-1.0, -1e-3]])
    state = ControllerState(np.array([[math.pi - 0.001, 0.0, 1.0, 0.0, 0.0]]))
    out = compute_commands(p, [math.pi], p_d, [[0, 0]], 0.0, 0.0, g, state, 0.1)
    assert abs(out.a_r_dot[0]) < 0.1


def test_undefined_reference_angle_is_held_not_spun():
    # Leader stopped, follower on its slot: zeta_r = 0 and a_r would be atan2(0, 0).
    g = Gains()
    out = compute_commands([[0.5, -0.3]], [1.0], [[0.5, -0.3]], [[0, 0]], 0.0, 0.0, g,
                           ControllerState.initial(1), 0.01)
    assert_allclose(out.commands.v, [0.0], atol=1e-12)
    assert_allclose(out.commands.w, [0.0], atol=1e-12)


def test_inactive_followers_stop_at_once_despite_the_acceleration_limit():
    g = Gains()
    state = ControllerState(np.array([[1.0, 0.0, 1.0, 0.25, 1.5]] * 2))
    out = compute_commands([[0.0, 0.0]] * 2, [1.0, 1.0], [[1.0, 1.0]] * 2, [[0, 0]] * 2, 0.06, 0.0, g,
                           state, 0.01, active=[True, False])
    assert out.commands.v[1] == 0.0 and out.commands.w[1] == 0.0
    assert out.commands.v[0] != 0.0


@given(
    st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5), st.floats(-4, 4)), min_size=1, max_size=8),
    st.floats(-0.5, 0.5),
    st.floats(-1.0, 1.0),
    st.floats(0.01, 0.5),
    st.floats(0.05, 1.0),
)
def test_commands_never_exceed_the_hard_limits(poses, v_l, w_l, v_max, w_max):
    g = Gains(v_max=v_max, w_max=w_max)
    arr = np.array(poses)
    n = len(poses)
    state = ControllerState(np.column_stack([arr[:, 2], np.zeros(n), np.ones(n), np.full(n, 5.0), np.full(n, -9.0)]))
    out = compute_commands(arr[:, :2], arr[:, 2], np.zeros((n, 2)), np.zeros((n, 2)), v_l, w_l, g, state, 0.02)
    assert np.all(np.abs(out.commands.v) <= v_max + 1e-12)
    assert np.all(np.abs(out.commands.w) <= w_max + 1e-12)
    assert np.all(np.isfinite(out.commands.v)) and np.all(np.isfinite(out.commands.w))


def test_acceleration_limit_bounds_the_change_per_tick():
    g = Gains(accel_v_max=0.5, accel_w_max=5.0)
    out = compute_commands([[0.0, 0.0]], [0.0], [[1.0, 1.0]], [[0, 0]], 0.06, 0.0, g,
                           ControllerState.initial(1), 0.01)
    assert abs(out.commands.v[0]) <= 0.5 * 0.01 + 1e-12
    assert abs(out.commands.w[0]) <= 5.0 * 0.01 + 1e-12


def test_lyapunov_per_follower_and_team():
    v = lyapunov([[0.0, 0.0], [1.0, 1.0]], [[0.3, 0.4], [1.0, 1.0]])
    assert_allclose(v, [0.125, 0.0])


def test_gains_refuse_bad_values_with_the_allowed_range():
    with pytest.raises(ValueError, match=r"k_f1 = -0.1: must be a number in \(0, 1\] m/s"):
        Gains(k_f1=-0.1)
    with pytest.raises(ValueError, match=r"v_max = nan"):
        Gains(v_max=float("nan"))
    with pytest.raises(ValueError, match=r"a = 'x': must be a number"):
        Gains(a="x")  # type: ignore[arg-type]


def test_dt_must_be_positive():
    with pytest.raises(ValueError, match="dt = 0"):
        compute_commands([[0, 0]], [0], [[0, 0]], [[0, 0]], 0, 0, Gains(), ControllerState.initial(1), 0.0)
