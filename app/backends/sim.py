"""The built-in simulated team: world state, ground-truth observation, a follower link into it."""

from __future__ import annotations

import numpy as np

from core.sim.team import (
    FollowerDynamics,
    TeamState,
    make_team_state,
    measure_followers,
    step_team,
)
from core.types import Commands, FloatArray


class SimTeam:
    """A simulated leader and followers. The loop measures them, commands them, moves them."""

    def __init__(
        self,
        p0: FloatArray,
        a0: FloatArray,
        dynamics: FollowerDynamics,
        position_noise_m: float,
        heading_noise_rad: float,
        seed: int,
    ) -> None:
        self.state: TeamState = make_team_state(p0, a0)
        self.dynamics = dynamics
        self.position_noise_m = position_noise_m
        self.heading_noise_rad = heading_noise_rad
        self.rng = np.random.default_rng(seed)
        self.commands = Commands.zeros(len(a0))
        self.link_state = "simulated"

    # TeamObservation
    def observe(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        p, a = measure_followers(self.state, self.rng, self.position_noise_m, self.heading_noise_rad)
        return p, a, np.ones(len(a), dtype=bool)

    def truth(self) -> tuple[FloatArray, FloatArray]:
        return measure_followers(self.state, self.rng)

    # FollowerLink
    def send(self, commands: Commands) -> None:
        self.commands = commands

    def close(self) -> None:
        self.commands = Commands.zeros(self.state.n)

    def advance(self, leader_twist: tuple[float, float], dt: float, t: float) -> None:
        self.state = step_team(self.state, self.commands, leader_twist, dt, t, self.rng, self.dynamics)


def spread_start(n: int, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Start poses for n followers scattered around the leader (0.6-1.3 m away), random headings."""
    ang = np.pi / 2 + 2 * np.pi * (np.arange(n) + rng.uniform(-0.2, 0.2, n)) / n + np.pi / n
    r = rng.uniform(0.6, 1.3, n)
    return np.column_stack([r * np.cos(ang), r * np.sin(ang)]), rng.uniform(-np.pi, np.pi, n)
