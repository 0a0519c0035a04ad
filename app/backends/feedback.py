"""Where the loop's follower poses come from: the vision pipeline on camera frames (the
paper's way and the default), or the simulator's ground truth plus noise (to tune the
controller alone).

Both answer ``observe()`` with an :class:`Observation`; the vision one also asks for the
start-up manoeuvres of paper §3.1–3.2 and carries the frame for the camera panel.

The vision feedback takes its frames from the synthetic camera rendering the simulated team,
or from a real :class:`~app.backends.camera.FrameSource`. A real camera is asynchronous:
a tick with no new frame keeps the last estimates (the pipeline steps once per frame, with
the time and leader motion since the frame before), and a camera with no fresh frame for
``STALE_FRAME_S`` makes every follower untracked — the loop then commands zero.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from collections.abc import Callable

import numpy as np

from core.camera.lighting import Lighting, lighting_change, measure_lighting

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.camera.render import Renderer
from core.geometry import leader_displacement
from core.obstacles import Obstacle, as_array, seen_from
from core.sim.stepped import scan_settings_for, world_renderer
from core.types import FloatArray, Image
from core.vision.freespace import FreeSpaceScanner, ObstacleMemory, Scan, ScanSettings
from core.vision.pipeline import PipelineSettings, VisionPipeline

from app.contracts import FrameSource, Observation, SimulatedTeam, Team

STALE_FRAME_S = 0.3  # a camera frame older than this is no ground for moving a robot
LIGHTING_EVERY = 30  # frames between two looks at the floor's light (a second at 30 Hz)
SCAN_EVERY = 3  # frames between free-space scans (10 a second at 30 Hz, as a laser scanner gives them); the
# memory, moved by the odometry, holds the obstacles in between


class TruthFeedback:
    """Ground truth plus the configured noise: no camera, no start-up; the obstacles as the
    simulator knows them (the nearest point of each box to each robot)."""

    def __init__(self, team: SimulatedTeam, obstacles: tuple[Obstacle, ...] = ()) -> None:
        self.team = team
        self.boxes = as_array(obstacles)

    def observe(self, dt: float, commands: FloatArray, error_norm: FloatArray) -> Observation:
        at = time.monotonic()
        p, a, tracked = self.team.observe()
        known = seen_from(self.boxes, self.team.state.leader, self.team.truth()[0]) if len(self.boxes) else None
        return Observation(p, a, a.copy(), tracked, "truth", obstacles=known, observed_at=at)

    def scan_after(self) -> None:
        """No camera, no free-space scan (the truth knows the boxes)."""
        return None

    @property
    def scan_pending(self) -> bool:
        return False


@dataclass
class VisionFeedback:
    """A camera and the pipeline: the synthetic rig rendering ``team`` (no ``source``), or a
    real frame source (camera, video, folder)."""

    team: Team
    rig: CameraConfig
    gamma: Gamma
    seed: int
    source: FrameSource | None = None
    clock: Callable[[], float] = time.monotonic
    settings: PipelineSettings = field(default_factory=PipelineSettings)
    obstacles: tuple[Obstacle, ...] = ()  # the synthetic world's boxes (a scenario's), drawn by its camera
    scan: ScanSettings | None = None  # the free-space scan's heights (default: the synthetic rig's)
    # a fleet's arena: the synthetic camera draws every body of ``scene()`` ((k, 3) poses, leader frame) with
    # the marker hues ``scene_hues`` (NaN: none), not only the team; the team's own hues are known
    # (``hues_deg``, the start-up finds them by colour) and ``foreign_hues_deg`` are never taken for ours
    scene: Callable[[], FloatArray] | None = None
    scene_hues: tuple[float, ...] = ()
    hues_deg: tuple[float, ...] | None = None
    foreign_hues_deg: tuple[float, ...] = ()
    renderer: Renderer | None = field(init=False, default=None)
    pipeline: VisionPipeline | None = field(init=False, default=None)
    scanner: FreeSpaceScanner | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        n = self.team.state.n
        if self.source is None:
            model = self.rig.model
            if model is None:
                raise ValueError(f"{self.rig.source}: the simulated camera needs a [model]")
            rig = self.rig
            if self.scene is not None:  # the arena's bodies, each in its own hue; no furniture the arena does not have
                rig = replace(rig, render=replace(rig.render, hues_deg=self.scene_hues, clutter=False, distractor=False))
            self.renderer = world_renderer(rig, self.obstacles)
            self._make_pipeline((model.width, model.height))
        self._rng = np.random.default_rng(self.seed + 1)
        self._prev_leader = self.team.state.leader.copy()
        self._a_raw = np.full(n, np.nan)
        self._t = 0.0
        self._since_frame = 0.0
        self._frame_count = 0
        self._lit_at = -LIGHTING_EVERY
        self.lighting_note = ""  # the floor's light against the calibration's (core.camera.lighting)
        self._last: Observation | None = None
        self._scan_due = 0
        self.memory = ObstacleMemory(self.scanner.settings if self.scanner is not None else ScanSettings())
        self._pending: tuple[Image, FloatArray, np.ndarray, float] | None = None  # a scan due (scan_after)
        self._sampled: tuple[np.ndarray, FloatArray, np.ndarray, float, FloatArray] | None = None  # its first half done

    def _make_pipeline(self, size: tuple[int, int]) -> None:
        self.pipeline = VisionPipeline(self.team.state.n, self.gamma, self.rig.working_area, self.rig.detect,
                                       size, np.random.default_rng(self.seed), self.settings, self.hues_deg,
                                       self.foreign_hues_deg)
        heights = self.scan or (scan_settings_for(self.rig) if self.rig.model is not None else ScanSettings())
        self.scanner = FreeSpaceScanner(self.gamma, self.rig.working_area, heights)

    def observe(self, dt: float, commands: FloatArray, error_norm: FloatArray) -> Observation:
        t0 = time.perf_counter()
        observed_at = time.monotonic()  # the synthetic camera's frame is taken now; a real one's when it arrived
        bodies = self.scene() if self.scene is not None and self.source is None else None  # first: it may move the team's state
        state = self.team.state
        self._t += dt
        self._since_frame += dt
        camera_state = ""
        if self.source is None:
            assert self.renderer is not None
            if bodies is None:
                p_true, a_true = self.team.truth()
                bodies = np.column_stack([p_true, a_true])
            # rendered where the pipeline looks; the whole frame only when the dashboard or the
            # recorder asks for it, on their threads
            frame: Image | None = self.renderer.frame(state.leader, bodies, self._t - dt, self._rng)
        else:
            frame, t_frame, count = self.source.latest()
            camera_state = self.source.state
            settings = getattr(self.source, "settings_line", "")  # asked and got (app.backends.camera)
            if settings:
                camera_state = f"{camera_state} · {settings}"
            if self.lighting_note:
                camera_state = f"{camera_state} · {self.lighting_note}"
            age = self.clock() - t_frame
            if frame is None or age > STALE_FRAME_S:
                why = "no frame yet" if frame is None else f"no fresh frame for {age:.1f} s"
                return self._stale(f"camera: {why} ({camera_state})", camera_state)
            if count == self._frame_count and self._last is not None:
                return self._last  # no new frame this tick: the estimates of the newest one stand (and age)
            self._frame_count = count
            observed_at = t_frame
            if self.rig.lighting is not None and count - self._lit_at >= LIGHTING_EVERY:  # the light, now and then
                self._lit_at = count
                now = measure_lighting(frame, (self.gamma.cx, self.gamma.cy), self.rig.working_area)
                self.lighting_note = "" if now is None else lighting_change(Lighting(*self.rig.lighting), now)
            if self.pipeline is None:
                self._make_pipeline((frame.shape[1], frame.shape[0]))
        t1 = time.perf_counter()
        odometry = leader_displacement(self._prev_leader, state.leader)  # the leader's motion since the last frame
        self._prev_leader = state.leader.copy()
        assert self.pipeline is not None and frame is not None
        out = self.pipeline.step(frame, self._since_frame, odometry, commands, error_norm)
        self._since_frame = 0.0
        t2 = time.perf_counter()
        self.memory.move(odometry)
        known = None
        self._pending = None
        if out.manoeuvre is None and self.scanner is not None:  # not during the start-up: nobody is tracked yet
            self._scan_due -= 1
            if self._scan_due <= 0:  # a scan needs the whole ring rendered: SCAN_EVERY frames apart
                self._scan_due = SCAN_EVERY  # done by scan_after(), once this frame's commands are sent
                self._pending = (frame, out.positions, out.tracked, self._t)
            known = self.memory.current(self._t)
        t3 = time.perf_counter()
        fresh = np.isfinite(out.heading_measured)
        self._a_raw[fresh] = out.heading_measured[fresh]
        raw = np.where(np.isfinite(self._a_raw), self._a_raw, out.headings)
        self._last = Observation(out.positions, out.headings, raw, out.tracked, out.phase, out.manoeuvre, frame,
                                 out.windows, out.hues_deg, out.probing,
                                 {"camera": (t1 - t0) * 1e3, "vision": (t2 - t1) * 1e3, "obstacles": (t3 - t2) * 1e3},
                                 camera_state, known, observed_at)
        return self._last

    def scan_after(self) -> Scan | None:
        """The free-space scan, in two halves on two ticks, each once the tick's commands are sent
        (off the frame's way to the robots). On the tick a scan is due (every SCAN_EVERY frames)
        the ring of the frame ``observe`` stepped on is sampled (a synthetic camera renders it
        then); on the next, those samples are scanned into the obstacle memory, as of that
        frame's pose, and the scan returned. None on every other tick. What a scan finds is known
        from the tick after its second half: 66 ms after its frame at 30 Hz, against the 100 ms
        between two scans.

        Why halves: a whole scan (3 ms of CPU, more on a loaded machine) on one tick made that
        tick the long one of three, and the tick after it the one that started late. With
        leaders sharing a machine, the loops' rates held 30 Hz with 6 of them on a 2-core machine
        where they held it with 10 when no scan ran at all (`omniformation bench`, fleet line)."""
        done = None
        sampled, self._sampled = self._sampled, None
        if sampled is not None and self.scanner is not None:
            polar, positions, tracked, t, pose = sampled
            done = self.scanner.scan_samples(polar, positions, tracked)
            self.memory.update(done, t, np.where(tracked[:, None], positions, np.nan), pose)
        pending, self._pending = self._pending, None
        if pending is not None and self.scanner is not None:
            frame, positions, tracked, t = pending
            # the scanner's own array, kept until its next sample (SCAN_EVERY frames on)
            self._sampled = (self.scanner.sample(frame), positions, tracked, t, self.memory.pose)
        return done

    @property
    def scan_pending(self) -> bool:
        """A scan's ring is sampled and its scan due on the next tick (scan_after)."""
        return self._sampled is not None

    def _stale(self, phase: str, camera_state: str) -> Observation:
        """No usable frame: nobody is tracked and nothing moves (a zero manoeuvre keeps the
        loop from taking this for the end of the start-up)."""
        n = self.team.state.n
        last = self._last
        p = last.p if last is not None else np.full((n, 2), np.nan)
        a = last.a if last is not None else np.full(n, np.nan)
        raw = last.a_raw if last is not None else np.full(n, np.nan)
        return Observation(p, a, raw, np.zeros(n, dtype=bool), phase, np.zeros((n, 2)),
                           last.frame if last is not None else None, None, None, -1, {}, camera_state)

