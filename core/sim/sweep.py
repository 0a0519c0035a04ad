"""A step test in the simulator, and sweeps of it over a grid of gains.

:func:`step_scenario` turns a team's state (a scenario whose followers start where they are
now, each at its own slot) and a :class:`~core.control.tuning.StepTest` into a scenario that
runs ``lead_s`` seconds as it is, then applies the step (a formation switch for ``offset``
and ``switch``, a step of the leader's turn rate for ``turn``) and runs the test's window.
:func:`run_step_test` runs it in the stepped simulator (core.sim.stepped: the same slot
motion, controller and safety filter as the live loop) with ground truth plus the scenario's
noise, or with the vision pipeline on rendered frames, and scores it with
:func:`~core.control.tuning.score_step` on what the controller saw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.config import Scenario
from core.control.tuning import StepScore, StepTest, check_step_test, score_step, stepped_slots
from core.sim.profiles import Segment, SegmentsProfile
from core.sim.stepped import simulate_stepped
from core.types import FloatArray, Gains

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
    """Run ``test`` with ``gains`` from ``base`` (see :func:`step_scenario`) and score it."""
    scenario = step_scenario(base.replace(gains=gains), test, twist, lead_s)
    run = simulate_stepped(scenario, rig, gamma)
    log = run.log
    final = scenario.switches[-1][1] if scenario.switches else scenario.slots
    target = np.broadcast_to(np.asarray(final)[log.assignment], log.p_meas.shape)
    score = score_step(log.t, log.p_meas, target, log.commands, lead_s, test.window_s, scenario.dynamics.wheel_base_m)
    return StepRun(score, gains, lead_s)
