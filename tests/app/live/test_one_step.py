"""One control step for everything that drives a team (core.control.step): the live loop
and the stepped simulator, given the same scenario and seed, command the same thing tick by
tick. The loop runs its simulated team with truth feedback, ticked by hand (no clock).

Noise is off in both (measurement and wheels): each draws it from its own generator, and
what is compared here is the step, not the random streams."""

from __future__ import annotations

import dataclasses
import subprocess

import numpy as np
import pytest

from app.files import load_scenario
from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import ParamsStore
from app.services.live import params_for
from core.config import MeasurementNoise, Scenario
from core.sim.stepped import simulate_stepped

from tests.helpers import ROOT


def _quiet(scenario: Scenario, seconds: float) -> Scenario:
    return dataclasses.replace(scenario, duration_s=seconds, measurement=MeasurementNoise(0.0, 0.0),
                               dynamics=dataclasses.replace(scenario.dynamics, wheel_noise_mps=0.0))


def _live_commands(scenario: Scenario, ticks: int) -> tuple[np.ndarray, np.ndarray]:
    store = ParamsStore(params_for(scenario, scenario.n))
    loop = ServiceLoop(store, Backends(seed=scenario.seed, dynamics=scenario.dynamics, position_noise_m=0.0,
                                       heading_noise_rad=0.0, initial_poses=(scenario.initial_p, scenario.initial_a),
                                       obstacles=scenario.obstacles), rate_hz=scenario.rate_hz, switches=scenario.switches)
    states = [loop.tick() for _ in range(ticks)]
    loop.close_team()
    return np.array([s.commands for s in states]), np.array([s.followers_world for s in states])


@pytest.mark.parametrize("name, seconds, switches", [
    ("obstacle_course", 12.0, None),  # goal mode, three boxes, the filter on, the formation narrowed
    ("preset_swaps", 8.0, (1.0, 4.0)),  # the filter on, two formation switches (eq. 33 again, slots moving)
    ("paper_simulation", 6.0, None),  # the paper's §4 run: a constant twist, slots at rest
])
def test_the_loop_and_the_simulator_command_the_same_tick_by_tick(name, seconds, switches):
    scenario = _quiet(load_scenario(name), seconds)
    if switches is not None:  # the scenario's own switches, sooner
        scenario = dataclasses.replace(scenario, switches=tuple((t, slots) for t, (_, slots)
                                                                in zip(switches, scenario.switches)))
    sim = simulate_stepped(scenario).log
    ticks = len(sim.t)
    live, world = _live_commands(scenario, ticks)
    assert live.shape == sim.commands.shape
    moving = np.abs(sim.commands).max(axis=(1, 2)) > 1e-3
    assert moving.mean() > 0.5  # a run that drives, not one that stands still
    np.testing.assert_array_equal(live, sim.commands)
    np.testing.assert_array_equal(world, sim.followers_world)


def test_only_the_step_calls_the_controller_and_the_filter():
    """Nobody but core.control.step runs a team's controller, filter, slots or eq. 33 (the bench
    and the whole-run kernel of core/sim/run.py time or batch them, and say so)."""
    out = subprocess.run(["git", "grep", "--untracked", "-n", "-E", r"\b(compute_commands|filter_commands|step_slots|assign_slots)\(",
                          "--", "app", "core"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    callers = {line.split(":", 1)[0] for line in out.splitlines()}
    allowed = {"core/control/step.py", "core/control/formation.py", "core/control/safety.py",
               "core/control/targets.py", "core/control/assignment.py", "core/sim/run.py", "app/cli/bench/speed.py"}
    assert callers <= allowed, sorted(callers - allowed)
    assert "core/control/step.py" in callers
