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
) -> SlotMotion:
    """Move each desired position towards its target, |v| <= speed_max, |dv/dt| <= accel_max.

    The speed aimed for is min(speed_max, sqrt(2 accel_max d)) towards the
    target (d = remaining distance), so it arrives without overshoot; the
    velocity changes by at most accel_max dt per step.
    """
    tgt = np.atleast_2d(np.asarray(target, dtype=np.float64))
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
    left = tgt - p_new
    arrived = (np.hypot(left[:, 0], left[:, 1]) < 1e-6) & (
        np.hypot(motion.v_d[:, 0], motion.v_d[:, 1]) <= limit
    )
    p_new = np.where(arrived[:, None], tgt, p_new)
    v_new = np.where(arrived[:, None], 0.0, v_new)
    return SlotMotion(p_new, v_new)
