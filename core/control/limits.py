"""Hard command limits: every command is clamped to an acceleration limit and to v_max / w_max."""

from __future__ import annotations

import math

from numpy.typing import ArrayLike

from core.jit import ufunc
from core.types import FloatArray, Gains


@ufunc("float64(float64, float64, float64, float64)")
def clamp_command(value: float, previous: float, max_abs: float, max_step: float) -> float:
    """Clamp to previous +- max_step, then to +-max_abs; NaN becomes 0.

    The magnitude clamp comes last so that it holds even when the previous
    command was outside a (just lowered) limit.
    """
    if math.isnan(value):
        value = 0.0
    value = min(max(value, previous - max_step), previous + max_step)
    return min(max(value, -max_abs), max_abs)


def apply_command_limits(
    v: ArrayLike, w: ArrayLike, v_prev: ArrayLike, w_prev: ArrayLike, gains: Gains, dt: float
) -> tuple[FloatArray, FloatArray]:
    """Vectorised :func:`clamp_command` for (v, w) with the gains' limits."""
    return (
        clamp_command(v, v_prev, gains.v_max, gains.accel_v_max * dt),
        clamp_command(w, w_prev, gains.w_max, gains.accel_w_max * dt),
    )
