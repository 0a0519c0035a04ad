"""A step test in the simulator, and sweeps of it over a grid of gains.

:func:`step_scenario` turns a team's state (a scenario whose followers start where they are
now, each at its own slot) and a :class:`~core.control.tuning.StepTest` into a scenario that
runs ``lead_s`` seconds as it is, then applies the step (a formation switch for ``offset``
and ``switch``, a step of the leader's turn rate for ``turn``) and runs the test's window.
:func:`run_step_test` runs it in the stepped simulator (core.sim.stepped: the same slot
motion, controller and safety filter as the live loop) with ground truth plus the scenario's
noise, or with the vision pipeline on rendered frames, and scores it with
:func:`~core.control.tuning.score_step` on what the controller saw.

:func:`step_scenario` and :func:`settled_start` live beside the point function (core.study.point)
and are named here too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.config import Scenario
from core.control.tuning import GainRange, StepScore, StepTest
from core.study.point import LEAD_S, Step, run_point, settled_start, step_scenario
from core.types import Gains

__all__ = ["BEST_RULE", "LEAD_S", "METRICS", "STEADY_SLACK", "StepRun", "SweepResult", "run_step_test",
           "settled_start", "step_scenario"]

@dataclass(frozen=True)
class StepRun:
    score: StepScore
    gains: Gains
    t0: float


def run_step_test(
    base: Scenario,
    test: StepTest,
    twist: tuple[float, float],
    gains: Gains,
    rig: CameraConfig | None = None,
    gamma: Gamma | None = None,
    lead_s: float = LEAD_S,
) -> StepRun:
    """Run ``test`` with ``gains`` from ``base`` (see :func:`step_scenario`) and score it, through
    the one point function studies run too (core.study.point)."""
    outcome = run_point(base.replace(gains=gains), rig, gamma, Step(test, twist, lead_s))
    return StepRun(outcome.score, gains, lead_s)


METRICS = {  # what a sweep's heat map can show: (the score's key, scale, label with its unit, decimals)
    "settling": ("settling_s", 1.0, "settling time (s)", 1),
    "overshoot": ("overshoot_m", 100.0, "overshoot (cm)", 1),
    "steady error": ("steady_rms_m", 100.0, "steady error RMS (cm)", 2),
    "effort": ("effort", 1.0, "effort (m²/s)", 3),
}

STEADY_SLACK = (1.5, 0.0005)  # a settled point's steady RMS may be this × the best one's + this (m) and still rank
BEST_RULE = ("best: of the points that settle (within 2 cm), those whose steady error is at most 1.5 × the"
             " smallest steady error + 0.05 cm; of those the fastest to settle, then the least overshoot")


@dataclass(frozen=True)
class SweepResult:
    """Every point of a sweep in grid order (the first gain varies slowest); a point not run
    (cancelled) or failed has no score."""

    ranges: tuple[GainRange, ...]
    test: StepTest
    feedback: str  # "truth" or "vision"
    gains: tuple[Gains, ...]
    scores: tuple[StepScore | None, ...]
    seconds: float
    cancelled: bool = False
    errors: tuple[str, ...] = ()

    def values(self, k: int) -> tuple[float, ...]:
        """The swept gains' values at point k."""
        return tuple(float(getattr(self.gains[k], r.name)) for r in self.ranges)

    def point_label(self, k: int) -> str:
        s = self.scores[k]
        where = ", ".join(f"{r.name}={v:g}" for r, v in zip(self.ranges, self.values(k)))
        if s is None:
            return f"{where}: not run"
        w = s.worst
        settle = f"{w['settling_s']:.2f} s" if math.isfinite(w["settling_s"]) else "not settled"
        return f"{where}: settles {settle}, overshoot {w['overshoot_m'] * 100:.1f} cm, effort {w['effort']:.3f}"

    def order(self) -> list[int]:
        """Points from best to worst by :data:`BEST_RULE`: settled points whose steady error is
        within STEADY_SLACK of the best steady error among settled points, by settling time then
        overshoot; then the other settled points, by steady error; then the unsettled ones, by
        steady error; points not run last."""
        settled = [s.worst["steady_rms_m"] for s in self.scores
                   if s is not None and math.isfinite(s.worst["settling_s"]) and math.isfinite(s.worst["steady_rms_m"])]
        floor = min(settled) if settled else math.inf
        limit = floor * STEADY_SLACK[0] + STEADY_SLACK[1]

        def key(k: int) -> tuple[float, float, float]:
            s = self.scores[k]
            if s is None:
                return (3.0, math.inf, math.inf)
            w = s.worst
            if not math.isfinite(w["settling_s"]):
                return (2.0, w["steady_rms_m"], w["overshoot_m"])
            if w["steady_rms_m"] <= limit:
                return (0.0, w["settling_s"], w["overshoot_m"])
            return (1.0, w["steady_rms_m"], w["settling_s"])
        return sorted(range(len(self.gains)), key=key)

    def best(self) -> int | None:
        ranked = [k for k in self.order() if self.scores[k] is not None]
        return ranked[0] if ranked else None

    def pareto(self) -> list[int]:
        """The points no other point beats on both settling time and overshoot (settled ones)."""
        pts = [(k, s.worst) for k, s in enumerate(self.scores) if s is not None and math.isfinite(s.worst["settling_s"])]
        front = []
        for k, w in pts:
            if not any(o["settling_s"] <= w["settling_s"] and o["overshoot_m"] <= w["overshoot_m"]
                       and (o["settling_s"] < w["settling_s"] or o["overshoot_m"] < w["overshoot_m"]) for _, o in pts):
                front.append(k)
        return sorted(front, key=lambda k: self.scores[k].worst["settling_s"])  # type: ignore[union-attr]  # settled ones

    def table(self) -> list[dict[str, object]]:
        """One row per point: the swept values and the team's figures."""
        rows: list[dict[str, object]] = []
        for k in range(len(self.gains)):
            row: dict[str, object] = {r.name: v for r, v in zip(self.ranges, self.values(k))}
            s = self.scores[k]
            w = s.worst if s is not None else {}
            row.update({"settling_s": w.get("settling_s"), "overshoot_cm": w.get("overshoot_m", math.nan) * 100,
                        "steady_rms_cm": w.get("steady_rms_m", math.nan) * 100, "effort": w.get("effort")})
            rows.append(row)
        return rows

    def csv(self) -> str:
        rows = self.table()
        cols = [r.name for r in self.ranges] + ["settling_s", "overshoot_cm", "steady_rms_cm", "effort_m2_per_s"]
        lines = [",".join(cols)]
        for row in rows:
            vals = list(row.values())
            lines.append(",".join("" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.6g}"
                                  for v in vals))
        return "\n".join(lines) + "\n"

    def grid(self, key: str = "settling_s") -> np.ndarray:
        """The team's ``key`` over the grid, shape (len(values of gain 1), len(values of gain 2) or 1)."""
        shape = tuple(len(r.values) for r in self.ranges) + ((1,) if len(self.ranges) == 1 else ())
        vals = [s.worst[key] if s is not None else math.nan for s in self.scores]
        return np.array(vals, dtype=np.float64).reshape(shape)
