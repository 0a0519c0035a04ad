"""The contracts the loop is typed against: what a team, a feedback, a camera's frame source
and a follower link must offer, and the value a rig is (its camera config and Γ).

The loop (app.live.loop) knows only these shapes and imports nothing from app.backends; the
simulated team and real robots (app.backends.sim, app.backends.hardware, app.backends.arena), the
truth and vision feedbacks (app.backends.feedback), the cameras (app.backends.camera) and the
serial links (app.backends.serial_link) plug in behind them, and app.backends.world.Backends is
the :class:`World` the services hand the loop. What the loop needs of a real rig is said here as
members: a team's radio delay and leader link (:class:`Team`), a camera's real-time capture
thread (:class:`RealtimeFrameSource`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.obstacles import Obstacle
from core.sim.team import FollowerDynamics, TeamState
from core.types import BoolArray, Commands, FloatArray, Image
from core.vision.freespace import Scan


class Rig(NamedTuple):
    """A camera rig: its config (model, working area, detection) and the Γ that reads it."""

    camera: CameraConfig
    gamma: Gamma


class FrameSource(Protocol):
    """Where the loop's camera frames come from (a device, a video, a folder of images)."""

    name: str

    @property
    def state(self) -> str: ...

    def latest(self) -> tuple[np.ndarray | None, float, int]:
        """(newest BGR frame or None, monotonic time it arrived, its running number)."""
        ...

    def wait_newer(self, count: int, timeout: float) -> int:
        """Wait at most ``timeout`` s for a frame numbered above ``count``; the newest frame's
        number (``count`` if none came). The loop's ticks start on a camera's frames."""
        ...

    def close(self) -> None: ...


class RealtimeFrameSource(FrameSource, Protocol):
    """A frame source the loop's ticks start on (a real camera, a video, a folder of images)."""

    def make_realtime(self) -> str:
        """Ask real-time scheduling (app.realtime) for the source's own capture thread, as the loop
        does for its own with --realtime: "" when granted, else why not, in one line."""
        ...


class FollowerLink(Protocol):
    """Delivers each tick's commands to the robots on it and reports each robot's measured
    (v, w) from its wheel encoders (docs/follower-protocol.md)."""

    @property
    def link_state(self) -> str: ...

    @property
    def lost(self) -> bool:
        """No robot on the link answers: it commands zero whatever it is given."""
        ...

    def send(self, commands: Commands) -> None: ...

    def answering(self) -> BoolArray:
        """(n,) per robot: it answered a frame of ours, sent within the reply timeout, within that
        timeout. A robot that does not is commanded zero (the link sends it nothing else)."""
        ...

    def measured(self) -> tuple[FloatArray, FloatArray]: ...

    def detail(self) -> str: ...

    def close(self) -> None: ...


class Team(Protocol):
    """The robots the loop commands: the simulated team or real ones."""

    @property
    def state(self) -> TeamState: ...

    @property
    def link_state(self) -> str: ...

    @property
    def link_lost(self) -> bool:
        """The robots' link is lost: the loop commands zero until they answer again."""
        ...

    def link_detail(self) -> str: ...

    def answering(self) -> BoolArray:
        """(n,) the robots the loop may command: their link answers (all, for a simulated team)."""
        ...

    def truth(self) -> tuple[FloatArray, FloatArray]:
        """(p (n, 2), a (n,)) in the leader frame: the simulator's truth; NaN for real robots."""
        ...

    @property
    def leader_link(self) -> FollowerLink | None:
        """The leader's base, when it is a real one (its serial link, a ROS 2 base): the loop
        compensates what it measured (eq. 5); None: the commanded twist is the leader's."""
        ...

    def radio_delay_s(self) -> float | None:
        """How long a command takes to reach a real follower (half the link's mean round trip; 0
        before any answer): the loop predicts each pose over the frame's age and this (a real rig's
        latency, core.control.prediction). None for a team with no real rig to bridge (simulated,
        an arena's)."""
        ...

    def send(self, commands: Commands) -> None: ...

    def advance(self, leader_twist: tuple[float, float], dt: float, t: float) -> None:
        """Move the world (simulation) or the dead-reckoned leader (real rig) by one tick."""
        ...

    def close(self) -> None: ...


class SimulatedTeam(Team, Protocol):
    """A team whose truth the simulator (or a fleet's arena) knows: the truth feedback measures it."""

    def observe(self) -> tuple[FloatArray, FloatArray, BoolArray]:
        """(p (n, 2), a (n,), tracked (n,)) in the leader frame: the truth plus the configured noise."""
        ...


@dataclass(frozen=True)
class Observation:
    """What a feedback saw this tick."""

    p: FloatArray  # (n, 2) leader frame; NaN where never seen
    a: FloatArray  # (n,) filtered heading; NaN where unknown
    a_raw: FloatArray  # (n,) the last raw heading measurement (held), NaN before the first
    tracked: BoolArray  # (n,)
    phase: str  # "truth", the pipeline's phase (core.vision.pipeline.Phase), or a camera's trouble
    manoeuvre: FloatArray | None = None  # start-up commands the pipeline needs sent
    frame: Image | None = None  # BGR camera image (np.asarray for its pixels)
    windows: np.ndarray | None = None  # (n, 4) tracking windows (pixels)
    hues_deg: FloatArray | None = None
    probing: int = -1
    stage_ms: dict[str, float] = field(default_factory=dict)  # camera and pipeline times
    camera_state: str = ""  # a real camera's state for people ("" for the synthetic one)
    obstacles: FloatArray | None = None  # (k, 2) leader frame: obstacle points the leader knows (scan, memory, truth)
    observed_at: float = float("nan")  # monotonic time of what this is from: a camera frame's arrival, else the observing

    @property
    def ready(self) -> bool:
        return self.manoeuvre is None


class Feedback(Protocol):
    """Where the loop's follower poses come from: the truth plus noise, or the vision pipeline."""

    def observe(self, dt: float, commands: FloatArray, error_norm: FloatArray) -> Observation:
        """This tick's poses; ``commands`` (n, 2) and ``error_norm`` (n,) are the last tick's
        (the pipeline's heading update, eq. 34–37, and its Δs_min need them)."""
        ...

    def scan_after(self) -> Scan | None:
        """Called once the tick's commands are sent (off the frame's way to the robots): the
        free-space scan that was finished now, None on a tick that finished none (a camera's
        scan is taken every few frames, in halves on two ticks: VisionFeedback.scan_after)."""
        ...

    @property
    def scan_pending(self) -> bool:
        """A scan's first half is done and its second is due on the next tick."""
        ...


@dataclass(frozen=True)
class Made:
    """A team and its feedback, ready; ``start_p``: where the followers are known to start
    (leader frame; eq. 33 runs on it at once), None when the camera's start-up must find them."""

    team: Team
    feedback: Feedback
    start_p: FloatArray | None


class World(Protocol):
    """What the loop runs on, handed in by the services (app.backends.world.Backends is one): it
    makes the team and its feedback at the start and at every reset, and says what they are made of."""

    seed: int
    dynamics: FollowerDynamics
    position_noise_m: float
    heading_noise_rad: float
    camera: Rig | None
    obstacles: tuple[Obstacle, ...]

    @property
    def frames(self) -> RealtimeFrameSource | None:
        """A real camera's frames: the loop's ticks start on them (None: ticks at the loop's rate)."""
        ...

    def make(self, n: int, resets: int) -> Made:
        """The team of ``n`` followers after ``resets`` resets, and its feedback."""
        ...

    def robots(self) -> tuple[int, ...] | None:
        """An arena leader's: the fleet's robot index of each follower it drives (None elsewhere)."""
        ...

    def simulated(self, camera: Rig | None, obstacles: tuple[Obstacle, ...]) -> World:
        """A simulated world of the same kind (seed, dynamics, noise) seen through ``camera`` (None:
        the truth), with ``obstacles``: what the warm-up steps with nothing sent to any robot."""
        ...
