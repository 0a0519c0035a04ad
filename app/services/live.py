"""The long-running service: one loop thread, the viser server, the dashboard.

``Service.start()`` starts the loop in its own thread (the only thread that
steps the world); ``Service.close()`` stops it, which commands every follower
to zero, then stops the server. `omniformation run` runs one until Ctrl-C or
SIGTERM.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import cv2
import viser
from pathlib import Path

from core.config import MeasurementNoise, Scenario
from core.sim.team import FollowerDynamics
from core.types import FloatArray
from core.sim.profiles import ConstantProfile, Eq39Profile, GoalProfile

from app.backends.hardware import HardwareTeam
from app.backends.arena import ArenaTeam
from app.contracts import FollowerLink, RealtimeFrameSource, Rig
from app.dashboard import Dashboard, LatestStatePublisher
from app.dashboard.calibration_panel import CalibrationPanel
from app.dashboard.camera_panel import Overlay
from app.dashboard.tuning_panel import LiveBench, TuningPanel
from app.dashboard.gate import new_token, quietly, serve_gated
from app.dashboard.recordings_panel import RecordingsPanel
from app.services.page_process import PageProcess, goal_check_for  # (both processes' stores check a goal alike)
from app.services.page_tuning import serve_tuning
from app.services.replay import ReplayService
from app.live.loop import DEFAULT_NOISE, ServiceLoop
from app.backends.world import Backends
from app.params import LeaderMode, Params, ParamsStore, default_slots
from app.live.sweep import SweepRunner
from app.live.tuning import StepTests, live_base
from app.live.warmup import warm_up
from app.memory import bound_native_heap, bound_python_heap
from app.realtime import CpuReservation
from app.recording.reader import check_ticks, read_recording

# OpenCV's own threads in the loop's process: none. Its calls there are small (tracking windows of a few
# thousand pixels, the free-space scan's ring, about 400 x 400): handing each to a pool of workers, which
# spin while they wait for the next, took more CPU than it saved. Measured (`run --arena`, one vision
# leader, its process's CPU over 40 s, by turns): 23.7, 21.2 % with OpenCV's default pool; 20.7, 19.5 % with none.
LOOP_CV_THREADS = 0


def params_for(scenario: Scenario | None, n_followers: int) -> Params:
    """The operator's starting values: a scenario's, or the built-in team's."""
    if scenario is None:
        return Params(n_followers=n_followers, slots=default_slots(n_followers), leader_mode="straight")
    mode: LeaderMode = "straight"
    speed, turn = 0.06, 1.5
    lp = scenario.leader
    if isinstance(lp, ConstantProfile):
        mode = "circle" if lp.turn_rps else "straight"
        speed, turn = lp.speed_mps, math.degrees(lp.turn_rps) or 1.5
    elif isinstance(lp, Eq39Profile):
        mode, speed, turn = "eq39", lp.speed_mps, math.degrees(lp.k1_rps)
    goal = None
    if isinstance(lp, GoalProfile):
        mode, speed, goal = "goal", lp.speed_mps, lp.goal
    safety = scenario.safety
    return Params(gains=scenario.gains, leader_mode=mode, leader_speed_mps=speed, leader_turn_deg_s=turn,
                  slots=scenario.slots.copy(), n_followers=scenario.n, goal=goal, min_scale=scenario.min_scale,
                  safety_distance_m=safety.min_distance_m if safety is not None else Params.safety_distance_m)


class _NoPage:
    """Stands for the page's panels in the loop's process when the page runs in its own: the
    recording's name and state (``recording`` for the status, ``current`` for the Recordings panel)
    go to the page when the recorder asks for a rescan; the other writes go nowhere."""

    def __init__(self, page: PageProcess) -> None:
        self.controls = self
        self.page = page
        self.extra: list[Callable[[], None]] = []
        self.recording = ""
        self.current = ""
        self.health = self  # the page's alarms reach these listeners over the pipe (PageProcess.alarms)
        self.listeners: list[Callable[[float, str], None]] = []

    def rescan(self) -> None:
        self.page.show_recording(self.recording, self.current)


class Service:
    """``camera``: the synthetic rig and its Γ — the loop then sees the team through the vision
    pipeline; None feeds it the simulator's poses plus noise (``dynamics`` and ``noise`` apply)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, scenario: Scenario | None = None,
                 n_followers: int = 3, rate_hz: float = 30.0, seed: int = 0,
                 camera: Rig | None = None,
                 dynamics: FollowerDynamics | None = None, noise: MeasurementNoise | None = None,
                 link: FollowerLink | None = None, frames: RealtimeFrameSource | None = None,
                 hardware: HardwareTeam | None = None, recordings: Path | None = None,
                 token: str | None = None, arena: ArenaTeam | None = None, params: Params | None = None,
                 viewer_token: str | None = None, realtime: bool = False,
                 leader_base: FollowerLink | None = None, page_process: bool = False,
                 initial_poses: tuple[FloatArray, FloatArray] | None = None, reserve_cpu: bool = False) -> None:
        """``recordings``: the folder the Recordings panel lists (default: recordings/ in the working folder).
        ``token``: what clients must present (app.dashboard.gate); made up on a non-loopback host.
        ``arena``: this leader's robots in a fleet's arena (their count is the arena's, not the page's);
        ``params``: the operator's starting values when no scenario gives them.
        ``page_process``: the page (gate, viser, dashboard) in a process of its own, a client of this
        one's loop (app.services.page_process; the Tuning panel's work stays here, page_tuning).
        ``initial_poses``: where the simulated followers start (positions (n, 2), headings (n,))
        when no scenario says; else a seeded spread. ``reserve_cpu``: a CPU kept for the loop's
        thread, the service's other threads and the page's process off it (app.realtime.CpuReservation;
        `run --reserve-cpu`)."""
        bound_native_heap()  # hours of frames in bounded resident memory (app.memory)
        bound_python_heap()  # and of Python's small objects
        fixed = hardware.state.n if hardware is not None else len(arena.owned) if arena is not None \
            else getattr(link, "n", None)
        self.store = ParamsStore(params or params_for(scenario, fixed or n_followers), fixed_followers=fixed)
        noise = scenario.measurement if scenario is not None else noise or DEFAULT_NOISE
        if scenario is not None:
            initial_poses = (scenario.initial_p, scenario.initial_a)
            dynamics = scenario.dynamics
            seed = scenario.seed
        obstacles = scenario.obstacles if scenario is not None and hardware is None else ()
        world = Backends(seed=seed, dynamics=dynamics or FollowerDynamics(), position_noise_m=noise.position_noise_m,
                         heading_noise_rad=noise.heading_noise_rad, initial_poses=initial_poses, camera=camera,
                         link=link, frames=frames, hardware=hardware, obstacles=obstacles, arena=arena,
                         leader=leader_base)  # what the loop runs on, handed in (app.contracts.World)
        self.loop = ServiceLoop(self.store, world, rate_hz=rate_hz,
                                switches=scenario.switches if scenario is not None else (), realtime=realtime)
        if obstacles:
            self.store.goal_check = goal_check_for(obstacles)
        overlay = None
        if camera is not None:
            wa = camera[0].working_area
            overlay = Overlay((camera[1].cx, camera[1].cy), wa.inner_px, wa.outer_px)
        if reserve_cpu:
            self.loop.cpu = CpuReservation(lambda: [self.page.pid] if self.page is not None and self.page.pid else [])
        self.tests = StepTests(self.store, self.loop.dynamics.wheel_base_m)
        self.loop.subscribe(self.tests.on_tick)
        self.sweeps = SweepRunner()
        self._thread: threading.Thread | None = None
        self._closed = False
        self.page: PageProcess | None = None
        self.dashboard: Dashboard
        self.recordings: RecordingsPanel
        loop = self.loop

        def base() -> tuple[Scenario, tuple[float, float]] | str:
            return live_base(loop.last, self.store.get(), loop.dynamics,
                             MeasurementNoise(loop.position_noise_m, loop.heading_noise_rad), loop.rate_hz, loop.seed)

        synthetic = camera is not None and hardware is None and camera[0].model is not None
        self.bench = LiveBench(self.store, self.tests, self.sweeps, base, (lambda: camera) if synthetic else None)
        if page_process:
            self.page = PageProcess(self.store, host, port, token, viewer_token,
                                    None if overlay is None else (overlay.center, overlay.inner_px, overlay.outer_px),
                                    obstacles, rate_hz, recordings)
            self.page_tuning = serve_tuning(self.page, self.bench)  # the page's Tuning panel, its work here
            self.loop.subscribe(self.page.on_tick)
            self.page.dropped = lambda: self.loop.ticks_dropped  # the page's health banner judges them
            self.dashboard = self.recordings = _NoPage(self.page)  # type: ignore[assignment]  # what the recorder writes
            self.page.alarms = self.dashboard.controls.health.listeners  # the recorder's events
            if frames is not None and camera is not None:  # a real camera: the page's Calibration panel
                self.page.calibration = (camera[0].detect, (camera[1].cx, camera[1].cy), camera[0].working_area)
            self.page.launch()
            try:  # the loop's kernels warmed while the page's process starts (each takes a second or two);
                warm_up(self.loop)  # the loop's run() then finds them warm, its clock starting as before
                self.page.wait_ready()
            except BaseException:  # a page that cannot serve, Ctrl-C: its process ends with the rest
                self.page.close()
                raise
            return
        self.server, self.gate = serve_gated(host, port, token, viewer_token)

        def tuning(server: viser.ViserServer) -> TuningPanel:
            return TuningPanel(server, self.store, self.bench)

        self.dashboard = Dashboard(self.server, self.store, overlay, obstacles, tuning=tuning)
        self.gate.filter.allow_viewer(self.dashboard.controls.stop_button)  # stopping is always safe
        self.dashboard.controls.who = self.gate.who  # STOP names who pressed it
        self.dashboard.controls.health.target_hz, self.dashboard.controls.health.dropped = \
            self.loop.rate_hz, lambda: self.loop.ticks_dropped
        self.calibration: CalibrationPanel | None = None
        if frames is not None and camera is not None:  # a real camera: recalibrate it from the live page
            rig, gamma = camera
            self.calibration = CalibrationPanel(self.server, frames, rig.detect, Path("camera.toml"),
                                                centre=(gamma.cx, gamma.cy), area=rig.working_area)
            self.dashboard.extra.append(self.calibration.refresh)

        def replay(path: Path) -> ReplayService:
            """A replay with credentials of its own: the live page's token never goes into a link
            (the panel shows each client the link for its role; docs/page-access.md). A file that
            is no recording raises RecordingError (a ValueError), which the panel shows."""
            rec = read_recording(path)
            check_ticks(rec)
            return ReplayService(rec, host=host, port=0, token=new_token() if self.gate.token else None,
                                 viewer_token=new_token())

        self.recordings = RecordingsPanel(self.server, replay, recordings, role_of=self.gate.role_of)
        self.dashboard.controls.cause = lambda: self.recordings.cause("by the loop's own process")
        self.publisher = LatestStatePublisher(self.dashboard.publish)
        self.loop.subscribe(self.publisher)

    def show_line(self, text: Callable[[], str]) -> None:
        """A status line on the page (the fleet bus's), its text read from ``text`` a few times a second;
        with the page in its own process the text travels over the pipe."""
        if self.page is not None:
            self.page.add_line(text)
            return
        line = self.server.gui.add_markdown(text())

        def redraw() -> None:
            now = text()
            if line.content != now:
                line.content = now

        self.dashboard.extra.append(redraw)

    @property
    def url(self) -> str:
        return self.page.url if self.page is not None else self.gate.url

    @property
    def viewer_url(self) -> str:
        return self.page.viewer_url if self.page is not None else self.gate.viewer_url

    def start(self) -> None:
        if self.page is not None:  # this process is the loop's: its OpenCV calls on the calling thread
            cv2.setNumThreads(LOOP_CV_THREADS)
        self._thread = threading.Thread(target=self.loop.run, name="omniformation-loop", daemon=True)
        self._thread.start()

    def wait(self) -> None:
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(0.2)

    def close(self) -> None:
        """Stop the loop (it zeroes every follower as it ends), then the server and the camera.
        Waits for the tick in progress: the first one can take seconds while compiled code loads.
        A second call does nothing."""
        if self._closed:
            return
        self._closed = True
        self.loop.stop()
        if self._thread is not None:
            self._thread.join(60.0)
        else:  # never started: nothing else closes the team's link (a serial port left open would
            self.loop.close_team()  # keep reading whatever device later gets its name)
        self.sweeps.cancel()
        if self.page is not None:
            self.page.close()
            if self.loop.frames is not None:
                self.loop.frames.close()
            return
        self.publisher.close()
        self.recordings.close()
        self.gate.close()
        quietly(self.server.stop)
        if self.loop.frames is not None:
            self.loop.frames.close()
