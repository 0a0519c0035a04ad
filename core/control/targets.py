"""Moving desired positions smoothly: rho_d and rho_dot_d for eq. 3.

When the operator changes a slot, the desired position must not jump (that
would jump the command): it travels to the new target with bounded speed and
acceleration, and its velocity is fed to eq. 3 as rho_dot_d.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from core.types import FloatArray


@dataclass(frozen=True)
class SlotMotion:
    """Desired positions (n, 2) m and their velocity (n, 2) m/s, in the leader frame."""

    p_d: FloatArray
    v_d: FloatArray

    @staticmethod
    def at_rest(p_d: ArrayLike) -> "SlotMotion":
        p = np.atleast_2d(np.asarray(p_d, dtype=np.float64)).copy()
        return SlotMotion(p, np.zeros_like(p))


def step_slots(
    motion: SlotMotion,
    target: ArrayLike,
    dt: float,
    speed_max: float = 0.10,
    accel_max: float = 0.10,
    keep_out_m: float = 0.0,
) -> SlotMotion:
    """Move each desired position towards its target, |v| <= speed_max, |dv/dt| <= accel_max.

    The speed aimed for is min(speed_max, sqrt(2 accel_max d)) towards the
    target (d = remaining distance), so it arrives without overshoot; the
    velocity changes by at most accel_max dt per step.

    ``keep_out_m`` > 0: a desired position never crosses the leader's body: where the straight
    way to its target passes within this of the leader (the origin), it goes round on this
    circle, the shorter way, towards the side the target is on (``detour``). A follower that
    must get from in front of the leader to behind it then has a way the safety filter
    allows, instead of a target straight through the leader it would stall against.
    """
    tgt = np.atleast_2d(np.asarray(target, dtype=np.float64))
    final = tgt
    if keep_out_m > 0.0:
        tgt = detour(motion.p_d, tgt, keep_out_m)
    delta = tgt - motion.p_d
    dist = np.hypot(delta[:, 0], delta[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        direction = np.where(dist[:, None] > 0, delta / dist[:, None], 0.0)
    # Speed that still stops at the target with the available deceleration,
    # and never passes it within this step.
    wanted_speed = np.minimum(np.minimum(speed_max, np.sqrt(2.0 * accel_max * dist)), dist / dt)
    wanted_v = direction * wanted_speed[:, None]
    dv = wanted_v - motion.v_d
    dv_norm = np.hypot(dv[:, 0], dv[:, 1])
    limit = accel_max * dt
    scale = np.where(dv_norm > limit, limit / np.maximum(dv_norm, 1e-300), 1.0)
    v_new = motion.v_d + dv * scale[:, None]
    p_new = motion.p_d + v_new * dt
    # Snap when close enough and slow: no creeping forever around the target.
    tgt = final
    left = tgt - p_new
    arrived = (np.hypot(left[:, 0], left[:, 1]) < 1e-6) & (
        np.hypot(motion.v_d[:, 0], motion.v_d[:, 1]) <= limit
    )
    p_new = np.where(arrived[:, None], tgt, p_new)
    v_new = np.where(arrived[:, None], 0.0, v_new)
    return SlotMotion(p_new, v_new)


def detour(p: FloatArray, target: FloatArray, radius: float, step_rad: float = 0.6) -> FloatArray:
    """Per point, where to head for next: the target itself, or, when the segment p → target
    passes within ``radius`` of the origin (or within 0.95 of the target's own distance, if
    that is less), a point on the circle of 1.05 times that up to
    ``step_rad`` further round from p towards the target's angle, the shorter way."""
    p = np.atleast_2d(np.asarray(p, dtype=np.float64))
    t = np.atleast_2d(np.asarray(target, dtype=np.float64))
    d = t - p
    length2 = np.einsum("kd,kd->k", d, d)
    with np.errstate(invalid="ignore", divide="ignore"):
        along = np.clip(np.where(length2 > 0, -np.einsum("kd,kd->k", p, d) / length2, 0.0), 0.0, 1.0)
    closest = p + along[:, None] * d
    r = np.minimum(radius, 0.95 * np.hypot(t[:, 0], t[:, 1]))  # a target nearer than radius: round at its distance
    crosses = (np.hypot(closest[:, 0], closest[:, 1]) < r) & (np.hypot(p[:, 0], p[:, 1]) > 0.5 * r)
    if not crosses.any():
        return t
    ang_p = np.arctan2(p[:, 1], p[:, 0])
    turn = (np.arctan2(t[:, 1], t[:, 0]) - ang_p + np.pi) % (2 * np.pi) - np.pi
    ang = ang_p + np.clip(turn, -step_rad, step_rad)
    way = 1.05 * r[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    return np.where(crosses[:, None], way, t)
