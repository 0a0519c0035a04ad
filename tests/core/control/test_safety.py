"""The barrier-certificate safety filter: robots driven at each other, at the leader and at an
obstacle keep their distance on ideal unicycles in the leader frame (eq. 26); commands that are
already safe pass untouched; a failed solve stops only the robots near something."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.control.safety import SafetySettings, barrier_constraints, filter_commands, team_min_distance
from core.types import Commands

S = SafetySettings()
DT = 1 / 30


def step(p: np.ndarray, a: np.ndarray, c: Commands, twist: tuple[float, float], dt: float = DT) -> tuple:
    """Ideal unicycles seen from the leader (eq. 26): ṗ = v(cos a, sin a) − ζ̇_comp(p), ȧ = ω − ω_l."""
    v_l, w_l = twist
    comp = np.column_stack([-w_l * p[:, 1], v_l + w_l * p[:, 0]])
    p = p + dt * (np.column_stack([c.v * np.cos(a), c.v * np.sin(a)]) - comp)
    return p, a + dt * (c.w - w_l)


def drive(p, a, nominal, twist=(0.0, 0.0), obstacles=None, seconds=6.0, s=S):
    closest, obstacle_gap = np.inf, np.inf
    for _ in range(int(seconds / DT)):
        res = filter_commands(p, a, nominal(p, a), twist, obstacles, s, limits=(0.3, 2.0))
        assert res.status in ("inactive", "filtered"), res.message
        p, a = step(p, a, res.commands, twist)
        closest = min(closest, team_min_distance(p))
        if obstacles is not None:
            gaps = np.linalg.norm(p[:, None, :] - obstacles[None, :, :2], axis=-1) - obstacles[None, :, 2]
            obstacle_gap = min(obstacle_gap, float(gaps.min()))
    return p, a, closest, obstacle_gap


def test_two_followers_driven_head_on_keep_the_minimum_distance():
    p0 = np.array([[-0.8, 0.6], [0.8, 0.6]])
    a0 = np.array([0.0, np.pi])
    ahead = Commands(np.full(2, 0.2), np.zeros(2))
    p, a, unfiltered = p0, a0, np.inf
    for _ in range(int(6 / DT)):  # without the filter they drive through each other
        p, a = step(p, a, ahead, (0.0, 0.0))
        unfiltered = min(unfiltered, team_min_distance(p))
    assert unfiltered < 0.02
    _, _, closest, _ = drive(p0, a0, lambda p, a: ahead)
    assert closest >= S.min_distance_m - 0.005  # centre to centre (one 30 Hz step of slack)


def test_the_leader_body_is_kept_clear_while_it_drives():
    p = np.array([[0.0, 1.0]])
    a = np.array([-np.pi / 2])  # facing the leader, which drives at it at 0.1 m/s
    _, _, closest, _ = drive(p, a, lambda p, a: Commands(np.full(1, 0.15), np.zeros(1)), twist=(0.1, 0.0))
    assert closest >= S.min_distance_m - 0.005


def test_an_obstacle_is_kept_clear():
    obstacles = np.array([[0.0, 1.2, 0.15]])
    p = np.array([[-1.0, 1.2]])
    a = np.array([0.0])
    _, _, _, gap = drive(p, a, lambda p, a: Commands(np.full(1, 0.2), np.zeros(1)), obstacles=obstacles)
    assert gap >= S.obstacle_margin_m + S.follower_radius_m - 0.005


def test_commands_that_are_already_safe_pass_untouched():
    p = np.array([[-1.0, 0.5], [1.0, 0.5], [0.0, -1.2]])
    a = np.array([0.3, 2.0, -1.0])
    c = Commands(np.array([0.1, -0.05, 0.2]), np.array([0.3, 0.0, -0.2]))
    res = filter_commands(p, a, c, (0.06, 0.02))
    assert res.status == "inactive" and res.commands is c and not res.active.any()


def test_a_failed_solve_stops_the_robots_near_something_and_only_them():
    p = np.array([[-0.16, 0.8], [0.16, 0.8], [0.0, -1.5]])
    a = np.array([0.0, np.pi, 0.0])
    c = Commands(np.array([0.2, 0.2, 0.1]), np.array([0.0, 0.0, 0.1]))
    res = filter_commands(p, a, c, (0.0, 0.0), settings=SafetySettings(solver="no-such-solver"))
    assert res.status == "no solver" and "no-such-solver" in res.message
    assert np.all(res.commands.v[:2] == 0) and np.all(res.commands.w[:2] == 0)
    assert res.commands.v[2] == 0.1 and res.commands.w[2] == 0.1


def test_untracked_followers_get_no_constraint():
    p = np.array([[0.0, 0.0], [0.1, 0.8]])  # the first is unknown: its placeholder sits on the leader
    a = np.array([0.0, 0.0])
    _, _, constrained = barrier_constraints(p, a, (0.0, 0.0), np.zeros((0, 3)), S, known=np.array([False, True]))
    assert not constrained[0] and not constrained[1]


def test_bad_settings_are_refused_in_one_line():
    with pytest.raises(ValueError, match="safety min_distance_m = -1: must be a positive number"):
        SafetySettings(min_distance_m=-1)


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 6), st.integers(0, 2**31 - 1))
def test_the_filtered_commands_keep_every_barrier_and_the_limits(n, seed):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1.0, 1.0, (n, 2))
    p += 0.35 * np.sign(p)  # off the leader's body
    a = rng.uniform(-np.pi, np.pi, n)
    c = Commands(rng.uniform(-0.3, 0.3, n), rng.uniform(-2.0, 2.0, n))
    twist = (float(rng.uniform(0, 0.1)), float(rng.uniform(-0.05, 0.05)))
    res = filter_commands(p, a, c, twist, limits=(0.3, 2.0))
    if res.status == "infeasible":  # robots already inside each other's distance may leave no way out
        assert np.all(res.commands.v[res.constrained] == 0)
        return
    assert res.status in ("inactive", "filtered")
    G, h, _ = barrier_constraints(p, a, twist, np.zeros((0, 3)), S)
    ahead = S.projection_m
    u = np.column_stack([np.cos(a) * res.commands.v - ahead * np.sin(a) * res.commands.w,
                         np.sin(a) * res.commands.v + ahead * np.cos(a) * res.commands.w]).reshape(-1)
    assert np.all(G @ u <= h + 1e-6 * np.maximum(1.0, np.abs(h)))
    assert np.all(np.abs(res.commands.v) <= 0.3 + 1e-6) and np.all(np.abs(res.commands.w) <= 2.0 + 1e-6)


def test_load_solver_solves_a_binding_qp_and_names_a_missing_solver():
    """The warm-up's solve (app.live.warmup) goes to the solver and is solved ("filtered"); a
    solver that is not installed is said, not raised."""
    from core.control.safety import load_solver

    assert load_solver(SafetySettings().solver) == "filtered"
    assert load_solver("no-such-solver") == "no solver"
