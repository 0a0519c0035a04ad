import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from core.control.assignment import assign_slots, assignment_cost, assignment_cost_matrix


def test_eq33_cost_is_squared_distance():
    c = assignment_cost_matrix([[0.0, 0.0], [1.0, 1.0]], [[0.0, 1.0], [3.0, 1.0]])
    assert_allclose(c, [[1.0, 10.0], [1.0, 4.0]])


def test_paper_simulation_assignment_keeps_left_follower_on_the_left_slot():
    a = assign_slots([[-0.70, -0.80], [0.30, -0.90]], [[0.50, -0.30], [-0.50, -0.30]])
    assert list(a) == [1, 0]


@settings(max_examples=60)
@given(st.integers(1, 5), st.integers(0, 2), st.integers(0, 2**31 - 1))
def test_minimum_total_cost_equals_brute_force(n, extra, seed):
    rng = np.random.default_rng(seed)
    p = rng.uniform(-2, 2, (n, 2))
    s = rng.uniform(-2, 2, (n + extra, 2))
    got = assign_slots(p, s)
    cost = assignment_cost_matrix(p, s)
    best = min(assignment_cost(cost, perm) for perm in itertools.permutations(range(n + extra), n))
    assert len(set(got.tolist())) == n
    assert_allclose(assignment_cost(cost, got), best, atol=1e-12)


def test_current_assignment_is_kept_unless_clearly_cheaper():
    slots = [[-0.5, 0.0], [0.5, 0.0]]
    # Two followers almost equidistant: the swap saves very little.
    p = [[0.01, 0.0], [-0.01, 0.0]]
    current = np.array([0, 1])
    assert list(assign_slots(p, slots)) == [1, 0]
    assert list(assign_slots(p, slots, current=current, margin_m2=0.05)) == [0, 1]
    # Far off: the optimum wins despite the margin.
    p_far = [[0.5, 0.0], [-0.5, 0.0]]
    assert list(assign_slots(p_far, slots, current=current, margin_m2=0.05)) == [1, 0]


def test_invalid_current_assignment_is_replaced():
    got = assign_slots([[0, 0], [1, 0]], [[0, 0], [1, 0]], current=np.array([0, 0]), margin_m2=10.0)
    assert list(got) == [0, 1]


def test_too_few_slots_is_refused():
    with pytest.raises(ValueError, match="3 followers need at least 3 slots, got 2"):
        assign_slots(np.zeros((3, 2)), np.zeros((2, 2)))
