"""Where each follower will be when its next command acts: the robots' own odometry run forward
over the latency (the paper's prediction between frames, eq. 34-38, over the commands already
sent). Pure; vectorised over followers.

Seen from the leader frame a follower moves as ṗ = v·(cos a, sin a) − ζ̇_comp(p) and
ȧ = ω − ω_l (eq. 26), with ζ̇_comp(p) = (−ω_l·y, v_l + ω_l·x) the velocity of a point fixed to
the leader (docs/paper-notes.md). An observation that is ``k`` ticks old, and commands that act
``r`` ticks after they are sent, leave the controller k + r ticks to bridge: the commands applied
in each of those ticks are known (they were sent before), the leader's twist too (recorded, and
the current one for the ticks to come).
"""

from __future__ import annotations

import numpy as np

from core.geometry import wrap_angle
from core.types import FloatArray


def predict_poses(p: FloatArray, a: FloatArray, commands: FloatArray, twists: FloatArray,
                  dt: float) -> tuple[FloatArray, FloatArray]:
    """(p (n, 2), a (n,)) in the leader frame after ``len(commands)`` ticks: ``commands`` (k, n, 2)
    the (v, ω) each follower applied in each tick, ``twists`` (k, 2) the leader's (v_l, ω_l)."""
    p = np.array(p, dtype=np.float64, copy=True)
    a = np.array(a, dtype=np.float64, copy=True)
    for (v_l, w_l), cmd in zip(np.asarray(twists, dtype=np.float64), np.asarray(commands, dtype=np.float64)):
        v, w = cmd[:, 0], cmd[:, 1]
        comp = np.column_stack([-w_l * p[:, 1], v_l + w_l * p[:, 0]])  # eq. 6-9, rigid-body form
        p = p + dt * (np.column_stack([v * np.cos(a), v * np.sin(a)]) - comp)
        a = a + dt * (w - w_l)  # eq. 26
    return p, np.asarray(wrap_angle(a))
