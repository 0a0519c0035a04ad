"""Hard command limits: every command is clamped to an acceleration limit and to v_max / w_max.

The controller kernel calls :func:`clamp_command` for each follower.
"""

from __future__ import annotations

import math

from core.jit import ufunc


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
