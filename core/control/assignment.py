"""Follower-to-slot assignment, paper §3.3 eq. 33: minimum total squared distance."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from core.types import FloatArray, IntArray


def assignment_cost_matrix(positions: ArrayLike, slots: ArrayLike) -> FloatArray:
    """Eq. 33: C[i, j] = squared distance from follower i (n, 2) to slot j (m, 2)."""
    p = np.atleast_2d(np.asarray(positions, dtype=np.float64))
    s = np.atleast_2d(np.asarray(slots, dtype=np.float64))
    d = p[:, None, :] - s[None, :, :]
    return np.einsum("ijk,ijk->ij", d, d)


def assignment_cost(cost: FloatArray, assignment: ArrayLike) -> float:
    """Total cost of an assignment (follower i -> slot assignment[i])."""
    idx = np.asarray(assignment, dtype=np.intp)
    return float(cost[np.arange(len(idx)), idx].sum())


def assign_slots(
    positions: ArrayLike,
    slots: ArrayLike,
    current: ArrayLike | None = None,
    margin_m2: float = 0.0,
) -> IntArray:
    """Slot index for each follower minimising the total squared distance (eq. 33).

    Needs at least as many slots as followers. With ``current`` (a valid
    assignment) the current one is kept unless the optimum is cheaper by more
    than ``margin_m2`` (m^2 of total cost), so measurement noise cannot make
    followers swap slots back and forth.
    """
    cost = assignment_cost_matrix(positions, slots)
    n, m = cost.shape
    if m < n:
        raise ValueError(f"{n} followers need at least {n} slots, got {m}")
    # imported at the first call (the loop's warm-up, before its clock), not by every process that
    # imports the control step (the page's): scipy.optimize takes ~0.7 s of CPU to import
    from scipy.optimize import linear_sum_assignment

    rows, cols = linear_sum_assignment(cost)
    best = np.empty(n, dtype=np.intp)
    best[rows] = cols
    if current is not None:
        cur = np.asarray(current, dtype=np.intp)
        valid = (
            cur.shape == (n,)
            and bool(np.all((cur >= 0) & (cur < m)))
            and len(set(cur.tolist())) == n
        )
        if valid and assignment_cost(cost, best) >= assignment_cost(cost, cur) - margin_m2:
            return cur.copy()
    return best
