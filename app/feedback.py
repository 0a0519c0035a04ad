"""Where the loop's follower poses come from: the vision pipeline on camera frames (the
paper's way and the default), or the simulator's ground truth plus noise (to tune the
controller alone).

Both answer ``observe()`` with an :class:`Observation`; the vision one also asks for the
start-up manoeuvres of paper §3.1–3.2 and carries the frame for the camera panel.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.camera.render import Renderer
from core.geometry import leader_displacement
from core.types import BoolArray, FloatArray
from core.vision.pipeline import VisionPipeline

from app.backends.sim import SimTeam


@dataclass(frozen=True)
class Observation:
    p: FloatArray  # (n, 2) leader frame; NaN where never seen
    a: FloatArray  # (n,) filtered heading; NaN where unknown
    a_raw: FloatArray  # (n,) the last raw heading measurement (held), NaN before the first
    tracked: BoolArray  # (n,)
    phase: str  # "truth" or the pipeline's phase
    manoeuvre: FloatArray | None = None  # start-up commands the pipeline needs sent
    frame: np.ndarray | None = None  # BGR camera image
    windows: np.ndarray | None = None  # (n, 4) tracking windows (pixels)
    hues_deg: FloatArray | None = None
    probing: int = -1
    stage_ms: dict[str, float] = field(default_factory=dict)  # camera and pipeline times

    @property
    def ready(self) -> bool:
        return self.manoeuvre is None


class TruthFeedback:
    """Ground truth plus the configured noise: no camera, no start-up."""

    def __init__(self, team: SimTeam) -> None:
        self.team = team

    def observe(self, dt: float, commands: FloatArray, error_norm: FloatArray) -> Observation:
        p, a, tracked = self.team.observe()
        return Observation(p, a, a.copy(), tracked, "truth")


@dataclass
class VisionFeedback:
    """A camera (here the simulated team seen through the synthetic rig) and the pipeline."""

    team: SimTeam
    rig: CameraConfig
    gamma: Gamma
    seed: int
    renderer: Renderer = field(init=False)
    pipeline: VisionPipeline = field(init=False)

    def __post_init__(self) -> None:
        model = self.rig.model
        if model is None:
            raise ValueError(f"{self.rig.source}: the simulated camera needs a [model]")
        self.renderer = Renderer(model, self.rig.render)
        self.pipeline = VisionPipeline(self.team.state.n, self.gamma, self.rig.working_area, self.rig.detect,
                                       (model.width, model.height), np.random.default_rng(self.seed))
        self._rng = np.random.default_rng(self.seed + 1)
        self._prev_leader = self.team.state.leader.copy()
        self._a_raw = np.full(self.team.state.n, np.nan)
        self._t = 0.0

    def observe(self, dt: float, commands: FloatArray, error_norm: FloatArray) -> Observation:
        state = self.team.state
        t0 = time.perf_counter()
        p_true, a_true = self.team.truth()
        frame = self.renderer.render(state.leader, np.column_stack([p_true, a_true]), self._t, self._rng)
        t1 = time.perf_counter()
        odometry = leader_displacement(self._prev_leader, state.leader)  # the LeaderOdometry of the sim
        self._prev_leader = state.leader.copy()
        out = self.pipeline.step(frame, dt, odometry, commands, error_norm)
        t2 = time.perf_counter()
        self._t += dt
        fresh = np.isfinite(out.heading_measured)
        self._a_raw[fresh] = out.heading_measured[fresh]
        raw = np.where(np.isfinite(self._a_raw), self._a_raw, out.headings)
        return Observation(out.positions, out.headings, raw, out.tracked, out.phase, out.manoeuvre, frame,
                           out.windows, out.hues_deg, out.probing,
                           {"camera": (t1 - t0) * 1e3, "vision": (t2 - t1) * 1e3})

