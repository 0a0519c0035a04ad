"""The stepped simulator: one Python step per tick, for what a whole-run kernel cannot do.

A scenario with obstacles, the safety filter, a goal for the leader or formation switches
(``Scenario.stepped``) runs here, with ground truth (plus the scenario's measurement noise)
or the vision pipeline on rendered frames as feedback. Each tick:

    observe (truth + noise, or frame → pipeline; with obstacles: the free-space scan and its
    memory, core.vision.freespace) → the leader's twist (its profile, or the goal navigator,
    core.control.navigation) → slots (switches, the navigator's scale; moved smoothly,
    core.control.targets) → controller (§2) → safety filter (core.control.safety) → world.

What the filter sees of the obstacles is what the leader would know: the scan's points with
vision, the boxes' nearest points with truth feedback. The log keeps what the truth says
(the closest two robots, the closest robot to an obstacle's surface), what the filter did,
and the scan.

The vision start-up of §3.1–3.2 takes simulated time, as on the real robots: the leader
stands still until the pipeline is ready, then its profile starts (scenario time 0). Log
rows before that have negative time. Disturbances ("stuck", "hidden") use scenario time.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.camera.render import Renderer
from core.config import Latency, Scenario
from core.control.prediction import predict_poses
from core.control.navigation import NavSettings, goal_in_leader_frame, navigate
from core.control.safety import team_min_distance
from core.control.step import TeamMemory, due, team_step
from core.geometry import heading_world_to_leader, leader_displacement, world_to_leader
from core.obstacles import Obstacle, as_array, seen_from, surface_distance
from core.sim.profiles import GoalProfile
from core.sim.run import SimulationLog
from core.sim.team import TeamState, disturbance_mask, make_team_state, step_team
from core.types import BoolArray, Commands, FloatArray, Image, IntArray
from core.vision.freespace import FreeSpaceScanner, ObstacleMemory, ScanSettings
from core.vision.pipeline import PipelineSettings, VisionPipeline


@dataclass(frozen=True)
class VisionLog:
    """A vision-in-the-loop run: the usual log (p_meas/a_meas are the pipeline's estimates)
    plus what only vision has."""

    log: SimulationLog
    tracked: BoolArray  # (T, n)
    heading_measured: FloatArray  # (T, n) eq. 34–37 measurements, NaN between them
    phase: tuple[str, ...]  # (T,)
    startup_s: float  # simulated time the start-up manoeuvres took
    windows: IntArray | None = None  # (T, n, 4) CAMSHIFT windows, pixels
    hues_deg: FloatArray | None = None  # (T, n) learned marker colours

    @property
    def n(self) -> int:
        return self.log.n


@dataclass(frozen=True)
class SafetyLog:
    """What keeps the team safe, per tick (truth where it says so)."""

    min_distance: FloatArray  # (T,) closest centres of two robots (followers and leader), truth
    obstacle_gap: FloatArray  # (T,) closest follower centre to an obstacle's surface, truth (inf: none)
    leader_gap: FloatArray  # (T,) the leader's centre to the nearest obstacle surface, truth (inf: none)
    status: tuple[str, ...]  # (T,) the filter's: inactive, filtered, infeasible, no solver, off
    changed: FloatArray  # (T, n) how much the filter moved each follower's command (m/s)
    limit_hits: FloatArray  # (T, n) bool: a command at |v| = v_max or |ω| = ω_max
    scale: FloatArray  # (T,) the formation's scale
    goal_reached_s: float  # scenario time the leader reached its goal (NaN: not, or no goal)
    scan_bearings: FloatArray | None = None  # (B,) with vision and obstacles
    scan_ranges: FloatArray | None = None  # (T, B) m, inf: free
    obstacle_points: tuple[FloatArray, ...] = ()  # per tick (k, 2), leader frame: what the filter saw


@dataclass(frozen=True)
class SteppedRun:
    log: SimulationLog
    safety: SafetyLog
    vision: VisionLog | None


def scan_settings_for(rig: CameraConfig) -> ScanSettings:
    """The scan's heights for a synthetic rig: its mirror and the markers its Γ was calibrated on."""
    assert rig.model is not None
    return ScanSettings(mirror_height_m=rig.model.mirror_height_m,
                        marker_height_m=rig.render.follower.height_m + 0.002,
                        follower_height_m=rig.render.follower.height_m)


def world_renderer(rig: CameraConfig, obstacles: tuple[Obstacle, ...]) -> Renderer:
    """The synthetic camera of a world with these obstacles drawn; a world with declared
    obstacles has no other furniture (the clutter would be obstacles the simulator does not know)."""
    assert rig.model is not None
    settings = replace(rig.render, clutter=False, distractor=False) if obstacles else rig.render
    return Renderer(rig.model, settings, obstacles)


class Delays:
    """A real rig's latency in the stepped simulator (core.config.Latency): observations reach the
    controller ``camera_s`` late, commands act ``radio_s`` after they are sent (each with up to
    ``jitter_s`` more, in whole ticks), the followers holding their last command in between; and
    the controller's prediction over both (core.control.prediction)."""

    def __init__(self, latency: Latency, dt: float, n: int, rng: np.random.Generator) -> None:
        self.latency, self.dt, self.n, self.rng = latency, dt, n, rng
        self.camera = int(round(latency.camera_s / dt))
        self.radio = int(round(latency.radio_s / dt))
        self.jitter = int(round(latency.jitter_s / dt))
        self.on = self.camera > 0 or self.radio > 0 or self.jitter > 0
        keep = self.camera + self.radio + self.jitter + 2
        self.seen: deque[tuple[FloatArray, FloatArray, BoolArray, FloatArray]] = deque(maxlen=keep)
        self.applied: deque[FloatArray] = deque(maxlen=keep)  # what the followers applied, tick by tick
        self.twists: deque[tuple[float, float]] = deque(maxlen=keep)  # the leader's twist, tick by tick
        self.queue: list[tuple[int, int, FloatArray]] = []  # (tick it acts, tick it was sent, command (n, 2))
        self.k = 0  # this tick
        self.age = 0  # how many ticks old this tick's observation is
        self.holding = np.zeros((n, 2))

    def _jitter(self) -> int:
        return int(self.rng.integers(0, self.jitter + 1)) if self.jitter else 0

    def observed(self, p: FloatArray, a: FloatArray, tracked: BoolArray,
                 known: FloatArray) -> tuple[FloatArray, FloatArray, BoolArray, FloatArray]:
        """This tick's observation in, the one the controller has now out (the oldest at first)."""
        self.seen.append((p, a, tracked, known))
        self.age = min(self.camera + self._jitter(), len(self.seen) - 1)
        return self.seen[-1 - self.age]

    def predicted(self, p: FloatArray, a: FloatArray, twist: tuple[float, float]) -> tuple[FloatArray, FloatArray]:
        """``p``, ``a`` (observed ``age`` ticks ago) run forward to when a command sent now acts:
        over the commands the followers applied since, those already on their way, and the
        leader's twists (the current one for the ticks to come)."""
        past = min(self.age, len(self.applied))
        commands = list(self.applied)[len(self.applied) - past:]
        twists = list(self.twists)[len(self.twists) - past:]
        holding = self.holding
        arriving = {at: c for at, _, c in sorted(self.queue, key=lambda q: (q[0], q[1]))}  # the newest sent wins a tick
        for j in range(self.k, self.k + self.radio):  # the commands already sent, as they will arrive
            holding = arriving.get(j, holding)
            commands.append(holding)
            twists.append(twist)
        if not commands:
            return p, a
        return predict_poses(p, a, np.array(commands), np.array(twists), self.dt)

    def sent(self, command: FloatArray, twist: tuple[float, float]) -> FloatArray:
        """This tick's command sent; what the followers apply this tick (held until a newer arrives)."""
        self.queue.append((self.k + self.radio + self._jitter(), self.k, np.array(command, dtype=np.float64)))
        due = [q for q in self.queue if q[0] <= self.k]
        if due:
            self.holding = max(due, key=lambda q: (q[0], q[1]))[2]
            self.queue = [q for q in self.queue if q[0] > self.k]
        self.applied.append(self.holding)
        self.twists.append(twist)
        self.k += 1
        return self.holding


class _Eyes:
    """What the leader knows each tick: the vision pipeline on rendered frames (and with
    obstacles or a goal the free-space scan and its memory), or the truth plus the scenario's
    measurement noise (and the boxes' nearest points). Draws from the run's generator in the
    run's order: the same seed, the same run."""

    def __init__(self, scenario: Scenario, rig: CameraConfig | None, gamma: Gamma | None, settings: PipelineSettings,
                 rng: np.random.Generator, on_frame: Callable[[int, Image], None] | None) -> None:
        self.scenario, self.rng, self.on_frame = scenario, rng, on_frame
        self.boxes = as_array(scenario.obstacles)
        self.renderer: Renderer | None = None
        self.pipeline: VisionPipeline | None = None
        self.scanner: FreeSpaceScanner | None = None
        self.memory = ObstacleMemory()
        if rig is not None:
            assert gamma is not None and rig.model is not None
            self.renderer = world_renderer(rig, scenario.obstacles)
            self.pipeline = VisionPipeline(scenario.n, gamma, rig.working_area, rig.detect,
                                           (rig.model.width, rig.model.height),
                                           np.random.default_rng(scenario.seed + 1), settings)
            if scenario.obstacles or isinstance(scenario.leader, GoalProfile):  # no obstacles scans empty: skip it
                self.scanner = FreeSpaceScanner(gamma, rig.working_area, scan_settings_for(rig))
                self.memory = ObstacleMemory(self.scanner.settings)

    def look(self, k: int, state: TeamState, p_true: FloatArray, a_true: FloatArray, t_wall: float,
             t_scn: float | None, odo: tuple[float, float, float], last_cmd: FloatArray, err_norm: FloatArray) -> tuple[
            FloatArray, FloatArray, BoolArray, FloatArray, Any, FloatArray | None, Any]:
        """(positions, headings, tracked, obstacle points, scan, start-up manoeuvre, pipeline output),
        all in the leader's frame; ``t_scn`` None: the start-up is still on."""
        n = self.scenario.n
        scan = manoeuvre = out = None
        if self.pipeline is not None and self.renderer is not None:
            hidden = disturbance_mask(self.scenario.disturbances, n, t_scn, "hidden")[0] if t_scn is not None else None
            # pixels are made only where the pipeline looks (bit for bit the whole frame's there)
            frame = self.renderer.frame(state.leader, np.column_stack([p_true, a_true]), t_wall, self.rng,
                                        hidden=hidden)
            if self.on_frame is not None:
                self.on_frame(k, frame)
            out = self.pipeline.step(frame, 1.0 / self.scenario.rate_hz, odo, last_cmd, err_norm)
            pos_m, head_m, tracked = out.positions, out.headings, out.tracked
            extra = self.scenario.measurement.vision_position_noise_m
            if extra > 0:  # drawn only when asked: a run without it is the same run as before
                pos_m = pos_m + self.rng.normal(0.0, extra, (n, 2))
            manoeuvre = out.manoeuvre
            if self.scanner is not None and manoeuvre is None:  # not during the start-up: nobody is tracked yet
                scan = self.scanner.scan(frame, pos_m, tracked)
        else:
            meas = self.scenario.measurement
            noise_p = self.rng.normal(0.0, meas.position_noise_m, (n, 2)) if meas.position_noise_m > 0 else 0.0
            noise_a = self.rng.normal(0.0, meas.heading_noise_rad, n) if meas.heading_noise_rad > 0 else 0.0
            pos_m, head_m, tracked = p_true + noise_p, a_true + noise_a, np.ones(n, dtype=bool)
        self.memory.move(odo)  # the obstacles as the leader knows them (leader frame)
        if scan is not None:
            known_pts = self.memory.update(scan, t_wall, np.where(tracked[:, None], pos_m, np.nan))
        else:
            known_pts = seen_from(self.boxes, state.leader, p_true)
        return pos_m, head_m, tracked, known_pts, scan, manoeuvre, out


def simulate_stepped(
    scenario: Scenario,
    rig: CameraConfig | None = None,
    gamma: Gamma | None = None,
    settings: PipelineSettings = PipelineSettings(),
    max_startup_s: float = 60.0,
    on_frame: Callable[[int, Image], None] | None = None,
    nav: NavSettings | None = None,
) -> SteppedRun:
    """Run ``scenario`` step by step; with ``rig`` and ``gamma`` the controller is fed by the
    vision pipeline on rendered frames, else by the truth plus the scenario's measurement noise.

    ``on_frame(k, frame)`` sees every frame (row k of the log), e.g. to record it;
    ``np.asarray(frame)`` renders the whole of it."""
    vision = rig is not None and gamma is not None
    if vision and rig is not None and rig.model is None:
        raise ValueError(f"{rig.source}: a vision simulation needs the rig's [model]")
    dt = 1.0 / scenario.rate_hz
    n = scenario.n
    rng = np.random.default_rng(scenario.seed)
    goal = scenario.leader if isinstance(scenario.leader, GoalProfile) else None
    nav = nav or NavSettings(speed_mps=goal.speed_mps if goal else NavSettings.speed_mps)
    eyes = _Eyes(scenario, rig if vision else None, gamma, settings, rng, on_frame)
    state = make_team_state(scenario.initial_p, scenario.initial_a)
    memory_c: TeamMemory | None = None  # the control step's, from the first estimates on
    smooth = bool(scenario.switches) or goal is not None  # slots that move: followed smoothly (as the live loop does)
    slots_now = scenario.slots
    p_d = np.zeros((n, 2))
    switch_k = 0
    scale = 1.0
    heading = math.nan
    reached_at = math.nan

    rows: dict[str, list[object]] = {k: [] for k in (
        "t", "leader", "twist", "fw", "p", "a", "pm", "am", "pd", "cmd", "aerr", "tracked", "meas", "phase", "win",
        "hue", "dmin", "gap", "lgap", "status", "changed", "limit", "scale", "scan", "obs")}
    prev_leader = state.leader.copy()
    last_cmd = np.zeros((n, 2))
    err_norm = np.zeros(n)
    delay = Delays(scenario.latency, dt, n, np.random.default_rng(scenario.seed + 7))  # its own draws: no other changes
    t_ready: float | None = None if vision else 0.0
    k = 0
    steps_after = int(round(scenario.duration_s * scenario.rate_hz)) + 1
    while True:
        t_wall = k * dt
        t_scn = t_wall - t_ready if t_ready is not None else -math.inf
        if t_ready is not None and int(round(t_scn / dt)) >= steps_after:
            break
        if t_ready is None and t_wall > max_startup_s:
            raise RuntimeError(f"{scenario.name}: the vision start-up did not finish in {max_startup_s:g} s")
        theta = float(state.leader[2])
        p_true = world_to_leader(state.followers[:, :2], state.leader[:2], theta)
        a_true = np.asarray(heading_world_to_leader(state.followers[:, 2], theta))
        odo = leader_displacement(prev_leader, state.leader)
        seen = eyes.look(k, state, p_true, a_true, t_wall, t_scn if t_ready is not None else None, odo, last_cmd,
                         err_norm)
        pos_m, head_m, tracked, known_pts, scan, manoeuvre, out = seen
        prev_leader = state.leader.copy()

        if delay.on:  # what reaches the controller is what the camera saw a while ago
            pos_m, head_m, tracked, known_pts = delay.observed(pos_m, head_m, tracked, known_pts)
        twist = (0.0, 0.0)
        status = "off"
        changed = np.zeros(n)
        if manoeuvre is not None:
            v_cmd, w_cmd = manoeuvre[:, 0], manoeuvre[:, 1]
            a_err = np.zeros(n)
        else:
            if vision and t_ready is None:
                t_ready = t_wall
                t_scn = 0.0
            known = np.where(np.isfinite(pos_m), pos_m, 0.0)
            if memory_c is None:
                memory_c = TeamMemory.start(known, scenario.slots)  # eq. 33 on the first estimates
            while switch_k < len(scenario.switches) and due(t_scn, scenario.switches[switch_k][0], dt):
                slots_now = scenario.switches[switch_k][1]
                switch_k += 1
            if goal is not None:
                g = goal_in_leader_frame(goal.goal, state.leader)  # odometry is exact in the simulator
                team_err = float(err_norm[tracked].max()) if tracked.any() else 0.0
                nav_out = navigate(g, known_pts, team_err, heading, scale, slots_now, scenario.min_scale, dt, nav)
                twist, heading, scale = nav_out.twist, nav_out.heading, nav_out.scale
                if nav_out.reached and not math.isfinite(reached_at):
                    reached_at = t_scn
            else:
                twist = tuple(float(x) for x in scenario.leader.twist(t_scn))  # type: ignore[assignment]  # a pair
            head = np.where(np.isfinite(head_m), head_m, math.pi / 2)
            # each follower where it will be when this command acts
            acting = delay.predicted(known, head, twist) if delay.on and delay.latency.compensate else None
            step = team_step(memory_c, known, head, tracked, slots_now, twist, scenario.gains, dt, obstacles=known_pts,
                             safety=scenario.safety, scale=scale, smooth=smooth, acting=acting, limits=False)
            memory_c = step.memory
            p_d = memory_c.slots.p_d
            if step.safety is not None:
                status, changed = step.safety.status, step.safety.changed
            v_cmd, w_cmd = np.asarray(step.control.commands.v), np.asarray(step.control.commands.w)
            a_err = step.control.a_err
            err_norm = step.err_norm

        last_cmd = np.column_stack([v_cmd, w_cmd])
        limit = (np.abs(v_cmd) >= scenario.gains.v_max - 1e-9) | (np.abs(w_cmd) >= scenario.gains.w_max - 1e-9)
        _add(rows, t=t_wall, leader=state.leader.copy(), twist=twist, fw=state.followers.copy(), p=p_true, a=a_true,
             pm=pos_m, am=head_m, pd=p_d.copy() if t_ready is not None else np.full((n, 2), np.nan),  # no target yet
             cmd=last_cmd, aerr=a_err, tracked=tracked, status=status, changed=changed, limit=limit, scale=scale,
             scan=scan.ranges if scan is not None else None, obs=known_pts)
        _truth_rows(rows, state, p_true, eyes.boxes)
        if vision:
            _add(rows, meas=out.heading_measured, phase=out.phase, win=out.windows, hue=out.hues_deg)

        applied = delay.sent(last_cmd, twist) if delay.on else last_cmd  # the radio's delay: what acts now
        state = step_team(state, Commands(np.asarray(applied[:, 0]), np.asarray(applied[:, 1])), twist, dt,
                          t_scn if t_ready is not None else -1.0, rng, scenario.dynamics,
                          scenario.disturbances if t_ready is not None else ())
        k += 1

    assert t_ready is not None
    assignment = np.asarray(memory_c.assignment if memory_c is not None else np.arange(n))
    return _run_from_rows(rows, scenario, t_ready, assignment, reached_at, eyes.scanner, vision)


def _add(rows: dict[str, list[object]], **values: object) -> None:
    for key, value in values.items():
        rows[key].append(value)


def _truth_rows(rows: dict[str, list[object]], state: TeamState, p_true: FloatArray, boxes: FloatArray) -> None:
    """What the truth says of safety this tick: the closest two robots, followers and leader to a box."""
    rows["dmin"].append(team_min_distance(p_true))
    rows["gap"].append(float(surface_distance(state.followers[:, :2], boxes).min()) if len(boxes) else math.inf)
    rows["lgap"].append(float(surface_distance(state.leader[None, :2], boxes).min()) if len(boxes) else math.inf)


def _run_from_rows(rows: dict[str, list[object]], scenario: Scenario, t_ready: float, assignment: IntArray,
                   reached_at: float, scanner: FreeSpaceScanner | None, vision: bool) -> SteppedRun:
    """The logs of a stepped run from its per-tick rows (time from the end of the start-up)."""
    t = np.array(rows["t"]) - t_ready
    log = SimulationLog(
        scenario=scenario,
        t=t,
        leader=np.array(rows["leader"]),
        leader_twist=np.array(rows["twist"], dtype=np.float64),
        followers_world=np.array(rows["fw"]),
        p=np.array(rows["p"]),
        a=np.array(rows["a"]),
        p_meas=np.array(rows["pm"]),
        a_meas=np.array(rows["am"]),
        p_d=np.array(rows["pd"]),
        commands=np.array(rows["cmd"]),
        a_err=np.array(rows["aerr"]),
        assignment=assignment,
    )
    scans: list[FloatArray] = [np.asarray(r) for r in rows["scan"] if r is not None]
    safety = SafetyLog(
        min_distance=np.array(rows["dmin"]), obstacle_gap=np.array(rows["gap"]), leader_gap=np.array(rows["lgap"]),
        status=tuple(str(x) for x in rows["status"]), changed=np.array(rows["changed"]),
        limit_hits=np.array(rows["limit"]), scale=np.array(rows["scale"]), goal_reached_s=reached_at,
        scan_bearings=scanner.bin_bearings if scanner is not None else None,
        scan_ranges=np.array([r if r is not None else np.full(scans[0].shape[0], np.nan) for r in rows["scan"]])
        if scans else None,
        obstacle_points=tuple(np.asarray(o) for o in rows["obs"]),
    )
    vlog = None
    if vision:
        vlog = VisionLog(log, np.array(rows["tracked"]), np.array(rows["meas"]), tuple(str(ph) for ph in rows["phase"]),
                         t_ready, np.array(rows["win"], dtype=np.int64), np.array(rows["hue"]))
    return SteppedRun(log, safety, vlog)
