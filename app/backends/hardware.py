"""The team when the robots are real: no simulator, no ground truth.

The loop asks its team for the leader's pose (for eq. 38 and the dashboard), sends it the
followers' commands, and advances it once per tick. Here:

* the followers' commands go to a follower link (the serial link), or nowhere ("observe
  only": e.g. checking the vision on a video file);
* the leader's pose is dead-reckoned from its base's wheel odometry — the LeaderOdometry
  port. The leader base speaks the followers' protocol at address 0 (docs/follower-
  protocol.md): it is sent the operator's (v, w) as SET_VELOCITY and its ACKs carry the
  encoder-measured (v, w). Without a leader base the leader is taken to stand still and
  the operator's leader motion is not applied;
* the followers' true poses are unknown (NaN), so the dashboard hides the "true" markers.
"""

from __future__ import annotations

import math

import numpy as np

from core.sim.team import TeamState, integrate_unicycle
from core.types import BoolArray, Commands, FloatArray

from app.contracts import FollowerLink


class HardwareTeam:
    def __init__(self, n: int, link: FollowerLink | None = None, leader: FollowerLink | None = None) -> None:
        self.link = link
        self.leader_link = leader
        self.state = TeamState(np.array([0.0, 0.0, math.pi / 2]), np.full((n, 3), np.nan), np.zeros((n, 2)))
        self.commands = Commands.zeros(n)

    @property
    def link_state(self) -> str:
        follower = "none (observe only)" if self.link is None else self.link.link_state
        leader = "" if self.leader_link is None else f" · leader base: {self.leader_link.link_state}"
        return follower + leader

    @property
    def link_lost(self) -> bool:
        return self.link is not None and self.link.lost

    def answering(self) -> BoolArray:
        """Observe only (no link): nothing is sent anyway, every robot counts as answering."""
        n = self.state.n
        return np.ones(n, dtype=bool) if self.link is None else np.asarray(self.link.answering(), dtype=bool)[:n]

    def radio_delay_s(self) -> float:
        """How long a command takes to reach a follower: half the link's mean round trip (0 with
        no link, or before any answer)."""
        rtts = [s.rtt_mean_ms for s in getattr(self.link, "stats", []) if math.isfinite(s.rtt_mean_ms)]
        return sum(rtts) / len(rtts) / 2e3 if rtts else 0.0  # on the frame's way: no numpy call

    def link_detail(self) -> str:
        parts = [x.detail() for x in (self.link, self.leader_link) if x is not None]
        return "; ".join(p for p in parts if p)

    def truth(self) -> tuple[FloatArray, FloatArray]:
        n = self.state.n
        return np.full((n, 2), np.nan), np.full(n, np.nan)

    def send(self, commands: Commands) -> None:
        self.commands = commands
        if self.link is not None:
            self.link.send(commands)

    def advance(self, leader_twist: tuple[float, float], dt: float, t: float) -> None:
        """Command the leader base and dead-reckon its pose from what its encoders measured."""
        if self.leader_link is None:
            return
        self.leader_link.send(Commands(np.array([leader_twist[0]]), np.array([leader_twist[1]])))
        v, w = self.leader_link.measured()
        pose = integrate_unicycle(self.state.leader, v[:1], w[:1], dt)[0]
        self.state = TeamState(pose, self.state.followers, self.state.follower_vel)

    def close(self) -> None:
        for link in (self.link, self.leader_link):
            if link is not None:
                link.close()
