"""The one point function: a scenario run and its score. `study`, `tune` and the page's sweeps
all run their points through :func:`run_point`, and all score with core.control.tuning's
:func:`~core.control.tuning.score_step`.

Two kinds of point:

* a **run from the scenario's start** (a study's default): the scenario as written (its start,
  its leader, its switches), scored from t = 0 to the end on the *true* positions against the
  formation's targets: does the formation get there and hold, whatever the controller was fed;
* a **step test** (`tune`, the page's sweeps, a study with ``[test]``): the team settled on its
  slots, the step at ``lead_s``, scored over the test's window on what the controller saw, as
  the live Tuning panel does.

The metrics (:data:`METRICS`) are the columns of a study's results.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.config import Scenario
from core.control.tuning import SETTLE_TOL_M, STEADY_S, StepScore, StepTest, check_step_test, score_step, stepped_slots
from core.sim.profiles import Segment, SegmentsProfile
from core.sim.runner import run_scenario
from core.sim.stepped import simulate_stepped
from core.types import FloatArray

# name -> (type, meaning); the order is the results' column order
METRICS: dict[str, tuple[str, str]] = {
    "converged": ("bool", "the team's error RMS within 2 cm at every tick of the last 2 s"),
    "settling_s": ("float", "from the start (or the step) until every follower stays within 2 cm; NaN: never"),
    "overshoot_m": ("float", "the largest overshoot past a target along the way to it (a follower that starts on it:"
                             " its peak error)"),
    "final_rms_m": ("float", "the team's error RMS over the last 2 s"),
    "max_error_m": ("float", "the largest error of any follower"),
    "effort": ("float", "∫ mean squared wheel speed dt, summed over the followers (m²/s)"),
    "min_distance_m": ("float", "the closest two robots' centres came (followers and leader)"),
    "collisions": ("int", "times two robots' bodies met: centres closer than their half-lengths added"),
    "tracking_lost_s": ("float", "vision: the seconds the worst-tracked follower was not tracked; 0 with truth"),
}
CONVERGED_RMS_M = SETTLE_TOL_M  # 2 cm
FOLLOWER_HALF_LENGTH_M = 0.125  # a follower is 25 cm long
LEADER_HALF_LENGTH_M = 0.25  # the leader's footprint as the scenario reader keeps obstacles clear of it


LEAD_S = 3.0  # the team runs this long before the step (the simulated followers start at rest: they catch up first)


def settled_start(scenario: Scenario) -> Scenario:
    """The scenario's team at rest on its slots (follower i on slot i, aligned with the leader):
    where a step test starts when no live state is given."""
    n = scenario.n
    return scenario.replace(initial_p=np.array(scenario.slots[:n], dtype=np.float64),
                            initial_a=np.full(n, np.pi / 2), slots=np.array(scenario.slots[:n], dtype=np.float64),
                            switches=(), disturbances=())


def step_scenario(base: Scenario, test: StepTest, twist: tuple[float, float], lead_s: float = LEAD_S) -> Scenario:
    """``base`` (follower i on slot i; the leader holding ``twist``) with the step at ``lead_s``."""
    why = check_step_test(test, base.n)
    if why:
        raise ValueError(why)
    v, w = twist
    leader = SegmentsProfile((Segment(0.0, v, w),))
    switches: tuple[tuple[float, FloatArray], ...] = ()
    if test.kind == "turn":
        leader = SegmentsProfile((Segment(0.0, v, w), Segment(lead_s, v, w + test.size)))
    else:
        switches = ((lead_s, stepped_slots(test, base.slots, np.arange(base.n))),)
    return base.replace(leader=leader, switches=switches, duration_s=lead_s + test.window_s, disturbances=())


@dataclass(frozen=True)
class Step:
    """A step test's part of a point: the test, the leader's twist, when the step comes."""

    test: StepTest
    twist: tuple[float, float]
    lead_s: float


@dataclass(frozen=True)
class Outcome:
    metrics: dict[str, Any]  # METRICS, by name
    score: StepScore  # per follower


def run_point(scenario: Scenario, rig: CameraConfig | None = None, gamma: Gamma | None = None,
              step: Step | None = None) -> Outcome:
    """Run one point and score it. ``scenario`` carries the point's values and the run's seed;
    with ``step``, it is the team settled on its slots (core.sim.sweep.settled_start)."""
    if step is None:
        run = run_scenario(scenario, rig, gamma)
        log = run.log
        tracked = run.vision.tracked if run.vision is not None else None
        return Outcome(*_score(log.t, log.p, log.p_d, log.commands, 0.0, scenario.duration_s,
                               scenario.dynamics.wheel_base_m, log.followers_world, log.leader, tracked,
                               scenario.rate_hz))
    stepped = step_scenario(scenario, step.test, step.twist, step.lead_s)
    srun = simulate_stepped(stepped, rig, gamma)
    log = srun.log
    final = stepped.switches[-1][1] if stepped.switches else stepped.slots
    target = np.broadcast_to(np.asarray(final)[log.assignment], log.p_meas.shape)
    tracked = srun.vision.tracked if srun.vision is not None else None
    return Outcome(*_score(log.t, log.p_meas, target, log.commands, step.lead_s, step.test.window_s,
                           stepped.dynamics.wheel_base_m, log.followers_world, log.leader, tracked, stepped.rate_hz))


def _score(t: FloatArray, p: FloatArray, target: Any, commands: FloatArray, t0: float, window_s: float,
           wheel_base_m: float, followers_world: FloatArray, leader: FloatArray, tracked: Any,
           rate_hz: float) -> tuple[dict[str, Any], StepScore]:
    score = score_step(t, p, target, commands, t0, window_s, wheel_base_m)
    worst = score.worst
    rows = np.flatnonzero((t >= t0 - 1e-9) & (t <= t0 + window_s + 1e-9))
    err = np.linalg.norm(np.asarray(p)[rows] - np.asarray(target)[rows], axis=-1)  # (K, n); NaN: not seen
    with np.errstate(invalid="ignore"):
        team_rms = np.sqrt(np.mean(err ** 2, axis=1))  # NaN if any follower was not seen
    last = t[rows] >= t[rows][-1] - STEADY_S if rows.size else np.zeros(0, dtype=bool)
    tail = team_rms[last]
    converged = bool(tail.size > 0 and np.all(np.isfinite(tail)) and np.all(tail <= CONVERGED_RMS_M))
    final_rms = worst["steady_rms_m"]  # the RMS over the last STEADY_S, as score_step measures it
    max_err = float(np.nanmax(err)) if np.isfinite(err).any() else math.nan
    dmin, hits = _proximity(np.asarray(followers_world)[rows], np.asarray(leader)[rows])
    lost = 0.0
    if tracked is not None:
        tr = np.asarray(tracked, dtype=bool)[rows]
        lost = float(np.max(np.sum(~tr, axis=0))) / rate_hz if tr.size else 0.0
    metrics = {"converged": converged, "settling_s": worst["settling_s"], "overshoot_m": worst["overshoot_m"],
               "final_rms_m": final_rms, "max_error_m": max_err, "effort": worst["effort"],
               "min_distance_m": dmin, "collisions": hits, "tracking_lost_s": lost}
    return metrics, score


def _proximity(followers_world: FloatArray, leader: FloatArray) -> tuple[float, int]:
    """The closest two robots' centres over the rows, and how many times two bodies met (a pair
    coming closer than its half-lengths added, counted once until it parts again)."""
    if followers_world.shape[0] == 0:
        return math.nan, 0
    pts = np.concatenate([leader[:, None, :2], followers_world[:, :, :2]], axis=1)  # (K, m, 2), leader first
    m = pts.shape[1]
    if m < 2:
        return math.nan, 0
    i, j = np.triu_indices(m, 1)
    d = np.linalg.norm(pts[:, i] - pts[:, j], axis=-1)  # (K, pairs)
    half = np.full(m, FOLLOWER_HALF_LENGTH_M)
    half[0] = LEADER_HALF_LENGTH_M
    touching = d < (half[i] + half[j])[None, :]
    starts = touching[0].astype(np.int64).sum() + np.count_nonzero(touching[1:] & ~touching[:-1])
    return float(np.min(d)), int(starts)
