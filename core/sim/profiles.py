"""Leader velocity profiles: constant, the paper's eq. 39 manoeuvre, piecewise segments."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from core.types import FloatArray


@dataclass(frozen=True)
class ConstantProfile:
    """v (m/s) and w (rad/s) for all t."""

    speed_mps: float
    turn_rps: float = 0.0

    def twist(self, t: float) -> tuple[float, float]:
        return self.speed_mps, self.turn_rps

    def twists(self, t: ArrayLike) -> FloatArray:
        """(len(t), 2) [v, w] for many times at once."""
        times = np.atleast_1d(np.asarray(t, dtype=np.float64))
        return np.column_stack([np.full(times.shape, self.speed_mps), np.full(times.shape, self.turn_rps)])


@dataclass(frozen=True)
class Eq39Profile:
    """Eq. 39: w_l(t) = k1 tanh(k2 (t1 - t)) for t_start <= t <= t_end, else 0; v constant.

    Paper §4: k1 = 1.5°/s, k2 = 0.2 1/s, t1 = 55 s, active 10-100 s. It starts
    at about +k1 (left turn) and ends at about -k1 (docs/paper-notes.md: the paper's
    sentence says the reverse).
    """

    speed_mps: float = 0.06
    k1_rps: float = math.radians(1.5)
    k2_per_s: float = 0.2
    t1_s: float = 55.0
    t_start_s: float = 10.0
    t_end_s: float = 100.0

    def twist(self, t: float) -> tuple[float, float]:
        if self.t_start_s <= t <= self.t_end_s:
            return self.speed_mps, self.k1_rps * math.tanh(self.k2_per_s * (self.t1_s - t))
        return self.speed_mps, 0.0

    def twists(self, t: ArrayLike) -> FloatArray:
        """(len(t), 2) [v, w] for many times at once."""
        times = np.atleast_1d(np.asarray(t, dtype=np.float64))
        inside = (times >= self.t_start_s) & (times <= self.t_end_s)
        w = np.where(inside, self.k1_rps * np.tanh(self.k2_per_s * (self.t1_s - times)), 0.0)
        return np.column_stack([np.full(times.shape, self.speed_mps), w])


@dataclass(frozen=True)
class Segment:
    """Hold (v, w) from t_start_s until the next segment starts."""

    t_start_s: float
    speed_mps: float
    turn_rps: float


@dataclass(frozen=True)
class SegmentsProfile:
    """Piecewise-constant (v, w); before the first segment the leader stands still."""

    segments: tuple[Segment, ...]

    def twist(self, t: float) -> tuple[float, float]:
        v, w = self.twists([t])[0]
        return float(v), float(w)

    def twists(self, t: ArrayLike) -> FloatArray:
        """(len(t), 2) [v, w] for many times at once."""
        times = np.atleast_1d(np.asarray(t, dtype=np.float64))
        starts = np.array([s.t_start_s for s in self.segments])
        table = np.array([[0.0, 0.0]] + [[s.speed_mps, s.turn_rps] for s in self.segments])
        return table[np.searchsorted(starts, times, side="right")]




@dataclass(frozen=True)
class GoalProfile:
    """The leader drives to a goal (world frame, m) around obstacles at up to ``speed_mps``
    (core.control.navigation): its twist depends on what it sees, not on time, so only the
    stepped simulator and the live loop drive it; as a time profile it stands still."""

    goal: tuple[float, float]
    speed_mps: float

    def twist(self, t: float) -> tuple[float, float]:
        return 0.0, 0.0

    def twists(self, t: ArrayLike) -> FloatArray:
        return np.zeros((np.asarray(t).size, 2))


LeaderProfile = ConstantProfile | Eq39Profile | SegmentsProfile | GoalProfile
