"""Which team the loop drives and how it sees it, made ready for the loop at its start and
at every reset: the simulated team (truth plus noise, or the synthetic camera), real robots
with a real camera, or this leader's robots in a fleet's arena. The loop types against the
contracts (app.contracts) and never builds a backend itself."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from core.obstacles import Obstacle
from core.sim.team import FollowerDynamics
from core.types import FloatArray
from core.vision.pipeline import PipelineSettings

from app.backends.arena import ArenaFeedback, ArenaTeam
from app.backends.feedback import TruthFeedback, VisionFeedback
from app.backends.hardware import HardwareTeam
from app.backends.sim import SimTeam, spread_start
from app.contracts import Feedback, FollowerLink, Made, RealtimeFrameSource, Rig

__all__ = ["Backends", "Made"]


@dataclass
class Backends:
    """What the loop runs on. ``camera``: the synthetic rig and its Γ (vision feedback), or a real
    rig's calibration with ``frames`` and ``hardware``; ``link``: real followers moving the
    simulated team (app.backends.sim); ``arena``: a fleet's arena; ``obstacles``: the simulated
    world's boxes (a scenario's)."""

    seed: int = 0
    dynamics: FollowerDynamics = field(default_factory=FollowerDynamics)  # ideal unless told (default.toml tells)
    position_noise_m: float = 0.003
    heading_noise_rad: float = float(np.radians(1.0))
    initial_poses: tuple[FloatArray, FloatArray] | None = None
    camera: Rig | None = None
    link: FollowerLink | None = None
    frames: RealtimeFrameSource | None = None
    hardware: HardwareTeam | None = None
    pipeline_settings: PipelineSettings = field(default_factory=PipelineSettings)
    obstacles: tuple[Obstacle, ...] = ()
    arena: ArenaTeam | None = None
    leader: FollowerLink | None = None  # the simulated team's leader base, when it is a real one (ROS 2)

    def __post_init__(self) -> None:
        if self.frames is not None and (self.hardware is None or self.camera is None):
            raise ValueError("a real frame source needs the real team (hardware) and the rig's calibration (camera)")

    def robots(self) -> tuple[int, ...] | None:
        """An arena leader's: the fleet's robot index of each follower it drives (None elsewhere)."""
        return tuple(self.arena.active) if self.arena is not None else None

    def simulated(self, camera: Rig | None, obstacles: tuple[Obstacle, ...]) -> Backends:
        """The simulated world of the same seed and dynamics, seen through ``camera`` (None: the truth),
        with ``obstacles``: no link, camera frames, real team or arena (app.contracts.World)."""
        return Backends(self.seed, self.dynamics, camera=camera, obstacles=obstacles)

    def make(self, n: int, resets: int) -> Made:
        """The team of ``n`` followers (a real or an arena's team: the robots it has) after
        ``resets`` resets: the simulated world starts afresh, each reset with its own draws."""
        feedback: Feedback
        vision_seed = self.seed + 2000 + resets
        if self.hardware is not None:  # real robots: the same team after a reset, the start-up runs again
            assert self.camera is not None
            return Made(self.hardware, VisionFeedback(self.hardware, self.camera[0], self.camera[1], vision_seed,
                                                      source=self.frames, settings=self.pipeline_settings), None)
        if self.arena is not None:  # a fleet's arena: the same robots after a reset, plus any adopted
            self.arena.resize(n)
            if self.camera is None:  # the truth, and the other teams as obstacles
                return Made(self.arena, ArenaFeedback(self.arena, TruthFeedback(self.arena)),
                            self.arena.observe()[0])
            own, foreign = self.arena.team_hues()  # its camera rendered from the arena; its team by their hues
            vision = VisionFeedback(self.arena, self.camera[0], self.camera[1], vision_seed,
                                    settings=self.pipeline_settings, scene=self.arena.scene,
                                    scene_hues=self.arena.scene_hues(), hues_deg=own, foreign_hues_deg=foreign)
            return Made(self.arena, ArenaFeedback(self.arena, vision), None)  # and the other teams as obstacles
        if self.initial_poses is not None and self.initial_poses[0].shape[0] == n:
            p0, a0 = self.initial_poses
        else:
            p0, a0 = spread_start(n, np.random.default_rng(self.seed + resets))
        team = SimTeam(p0, a0, self.dynamics, self.position_noise_m, self.heading_noise_rad,
                       self.seed + 1000 + resets, link=self.link, leader=self.leader)
        if self.camera is not None:
            feedback = VisionFeedback(team, self.camera[0], self.camera[1], vision_seed,
                                      settings=self.pipeline_settings, obstacles=self.obstacles)
            return Made(team, feedback, None)
        return Made(team, TruthFeedback(team, self.obstacles), p0)
