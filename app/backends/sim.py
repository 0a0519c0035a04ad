"""The built-in simulated team: world state, ground-truth observation, a follower link into it.

With a real follower link (``link``, e.g. the serial link to emulated followers) the commands
go over the wire instead, and the simulated followers move by what their wheel encoders
report back (the robots' own lag and limits are theirs, so the world uses ideal dynamics):
the camera then renders robots that the serial link really drives.
"""

from __future__ import annotations

import numpy as np

from core.sim.team import (
    FollowerDynamics,
    TeamState,
    make_team_state,
    measure_followers,
    step_team,
)
from app.contracts import FollowerLink
from core.types import BoolArray, Commands, FloatArray


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
        link: FollowerLink | None = None,
        leader: FollowerLink | None = None,
    ) -> None:
        """``leader``: a real leader base (e.g. a ROS 2 robot, app.backends.ros2): it is sent the
        leader's twist each tick and the simulated leader moves by what it measured."""
        self.state: TeamState = make_team_state(p0, a0)
        self.link = link
        self.leader = leader
        self._leader_sent = False  # the leader base was sent a twist since the last send()
        self.dynamics = dynamics if link is None else FollowerDynamics()
        self.position_noise_m = position_noise_m
        self.heading_noise_rad = heading_noise_rad
        self.rng = np.random.default_rng(seed)
        self.commands = Commands.zeros(len(a0))

    @property
    def link_state(self) -> str:
        state = "simulated" if self.link is None else self.link.link_state
        return state if self.leader is None else f"{state} · leader base: {self.leader.link_state}"

    @property
    def link_lost(self) -> bool:
        return self.link is not None and self.link.lost

    def answering(self) -> BoolArray:
        n = self.state.n
        return np.ones(n, dtype=bool) if self.link is None else np.asarray(self.link.answering(), dtype=bool)[:n]

    def link_detail(self) -> str:
        return "; ".join(x.detail() for x in (self.link, self.leader) if x is not None)

    def observe(self) -> tuple[FloatArray, FloatArray, BoolArray]:
        p, a = measure_followers(self.state, self.rng, self.position_noise_m, self.heading_noise_rad)
        return p, a, np.ones(len(a), dtype=bool)

    def truth(self) -> tuple[FloatArray, FloatArray]:
        return measure_followers(self.state, self.rng)

    @property
    def leader_link(self) -> FollowerLink | None:
        """The real leader base (``leader``), whose measured motion eq. 5 compensates."""
        return self.leader

    def radio_delay_s(self) -> None:
        """Simulated followers: no real rig's latency to bridge (real ones on ``link`` move a simulated world)."""
        return None

    def send(self, commands: Commands) -> None:
        self.commands = commands
        if self.leader is not None and not self._leader_sent:  # a tick that does not move the world (paused,
            self.leader.send(Commands.zeros(1))  # a fault): the base is told to stand, every tick
        self._leader_sent = False
        if self.link is not None:
            self.link.send(commands)

    def close(self) -> None:
        self.commands = Commands.zeros(self.state.n)
        for x in (self.link, self.leader):
            if x is not None:
                x.close()

    def advance(self, leader_twist: tuple[float, float], dt: float, t: float) -> None:
        moved = self.commands if self.link is None else Commands(*self.link.measured())
        if self.leader is not None:  # a real base: commanded, and the simulated leader moves as it measured
            self.leader.send(Commands(np.array([leader_twist[0]]), np.array([leader_twist[1]])))
            self._leader_sent = True
            v, w = self.leader.measured()
            leader_twist = (float(v[0]), float(w[0]))
        self.state = step_team(self.state, moved, leader_twist, dt, t, self.rng, self.dynamics)


def spread_start(n: int, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
    """Start poses for n followers scattered around the leader (0.6-1.3 m away), random headings."""
    ang = np.pi / 2 + 2 * np.pi * (np.arange(n) + rng.uniform(-0.2, 0.2, n)) / n + np.pi / n
    r = rng.uniform(0.6, 1.3, n)
    return np.column_stack([r * np.cos(ang), r * np.sin(ang)]), rng.uniform(-np.pi, np.pi, n)
