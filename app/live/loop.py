"""THE loop: observe -> assign -> controller -> follower link -> publish, at a fixed rate.

It owns time (monotonic clock, fixed tick dt); the dashboard and the recorder
only read the :class:`TickState` it publishes, and operator controls reach it
only through the :class:`ParamsStore`, read once per tick. On stop (Ctrl-C,
SIGTERM, an exception inside a tick) every follower is commanded to zero
before the loop returns.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from collections.abc import Callable

import numpy as np

from core.control.formation import ControlOutput
from core.control.navigation import NavOutput, NavSettings, goal_in_leader_frame, navigate
from core.control.prediction import predict_poses
from core.control.safety import SafetyResult, SafetySettings, team_min_distance
from core.control.step import TeamMemory, TeamStep, due, keep_out_m, step_limits, team_step
from core.control.tuning import RATE_WINDOW_S, lyapunov_rate
from core.config import MeasurementNoise
from core.obstacles import Obstacle
from core.sim.profiles import Eq39Profile
from core.sim.team import FollowerDynamics
from core.types import BoolArray, Commands, FloatArray

from app.live.warmup import compiled, warm_up
from app.realtime import SWITCH_INTERVAL_S, CpuReservation, make_realtime, scheduling
from app.contracts import Feedback, Observation, RealtimeFrameSource, Rig, Team, World
from app.params import Params, ParamsStore
from app.keys import follower_name
from app.tick import TickState

log = logging.getLogger(__name__)

DEFAULT_NOISE = MeasurementNoise(0.003, math.radians(1.0))  # truth feedback's noise unless told
# A loop late by up to CATCH_UP_S (and never less than CATCH_UP_TICKS ticks) runs the missed ticks
# at once and is back on its schedule; further behind, it starts afresh and the ticks it skipped are
# counted (ticks_dropped). On a shared machine the loop is sometimes kept off the CPU for 60-150 ms
# (a slow tick and a late wake-up in a row; a 66-minute soak measured it twice an hour): with a
# 100 ms allowance each such moment cost 3-4 ticks, 1 % of a 10 s window. Running the missed ticks
# is safe: each reads the newest frame and link state, the stale-frame and link checks go by the
# clock, not by ticks, and the robots hold the newest command (they never see a burst as speed).
CATCH_UP_S = 0.25
CATCH_UP_TICKS = 3
LATE_FRAME_PERIODS = 1.5  # frame-triggered ticks: no new frame within this many periods is a late camera
DT_RANGE = (0.25, 3.0)  # a frame-triggered tick's dt, as a share of the configured period, at least and at most


def next_tick(deadline: float, now: float, dt: float, late_limit: float) -> tuple[float, float, int]:
    """The pacing of :meth:`ServiceLoop.run`: after the tick due at ``deadline`` ended at ``now``,
    (the next tick's deadline, how long to wait for it, how many ticks are skipped). Late by up to
    ``late_limit``, the next tick runs at once (no wait) and the loop catches up; later still, the
    schedule starts afresh at ``now`` and the ticks it passed over are skipped."""
    due = deadline + dt
    late = now - due
    if late > late_limit:
        return now, 0.0, max(1, int(late / dt + 1e-9))  # whole ticks passed over (1e-9: 0.6 s is 18 ticks of 1/30 s)
    return due, -late, 0


@dataclass
class _World:
    team: Team
    feedback: Feedback
    memory: TeamMemory  # the control step's (core.control.step): controller, slots, assignment
    ready: bool = False  # the pipeline finished its start-up (always True for truth feedback)
    last_obs: Observation | None = None
    last_cmd: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))  # (n, 2) the last tick's commands
    err_norm: FloatArray = field(default_factory=lambda: np.zeros(0))  # (n,) the last tick's position errors
    v_hist: deque[tuple[float, FloatArray]] = field(default_factory=deque)  # (t, V (n,)) over RATE_WINDOW_S


def safety_text(result: SafetyResult | None, on: bool, name: Callable[[int], str] = follower_name) -> str:
    """The filter's state for people: what it changed this tick, and by how much (``name``: a
    follower's name, app.keys.follower_name)."""
    if not on:
        return "off"
    if result is None or result.status == "inactive":
        return "on, inactive"
    if result.status == "filtered":
        moved = [f"{name(int(i))} {result.changed[i]:.2f} m/s" for i in np.nonzero(result.active)[0]]
        return "on, changed " + (", ".join(moved) if moved else "no command noticeably")
    stopped = ", ".join(name(int(i)) for i in np.nonzero(result.active)[0])
    return f"on, {result.status}: {stopped or 'nobody'} stopped ({result.message})"


class ServiceLoop:
    """The one loop. ``tick()`` does one step; ``run()`` paces ticks until stopped."""

    def __init__(self, store: ParamsStore, world: World, rate_hz: float = 30.0, realtime: bool = False,
                 switches: tuple[tuple[float, FloatArray], ...] = ()) -> None:
        """``world``: what the loop runs on, handed in by the services (app.contracts.World;
        app.backends.world.Backends says what each kind of team and feedback is); the loop only
        drives what it makes. ``realtime``: the loop's thread (and a real camera's capture thread)
        ask for SCHED_FIFO when the loop starts (app.realtime); ``priority`` says what they got.
        ``switches``: (time s, slots) a scenario's formation switches, applied as the operator's
        would be (they count from the loop's start and from every reset)."""
        self.store = store
        self.dt = 1.0 / rate_hz
        self.rate_hz = rate_hz
        self.backends = world
        self.realtime = realtime
        self.cpu: CpuReservation | None = None  # a CPU kept for the loop's thread (the service sets it: --reserve-cpu)
        self.priority = "normal"  # how the loop's thread is scheduled, once it runs
        self.switches = tuple(switches)
        self._switch_k = 0
        self._nav = (math.nan, 1.0)  # the goal mode's last heading and formation scale
        self._nav_out: NavOutput | None = None
        self.faults = 0
        self.fault = ""
        self._subscribers: list[Callable[[TickState], None]] = []
        self._stop = threading.Event()
        self.tick_count = 0
        self.t = 0.0
        self._resets = 0
        self._steps_done = store.get().step_requests
        self._mode = ("", 0.0)
        self.achieved_rate_hz = 0.0
        self._longest_gap_s = 0.0  # between two tick starts, since the last take_longest_gap()
        self.ticks_dropped = 0  # ticks skipped since run() began: the loop was more than CATCH_UP_S late
        self.late_frames = 0  # frame-triggered ticks that ran without a new frame (a late camera)
        self._publish_ms: dict[str, float] = {}
        self._sent: deque[tuple[FloatArray, tuple[float, float]]] = deque(maxlen=30)  # (commands, twist) per tick
        self.leader_motion: tuple[tuple[float, float], str] = ((0.0, 0.0), "command")  # eq. 5's (v, w) and whence
        self.last: TickState | None = None
        self._safety: SafetySettings | None = None
        self._world = self._make_world(store.get())

    # what the team is made of (the world's own; read by the service, the tuning bench and run())
    @property
    def seed(self) -> int:
        return self.backends.seed

    @property
    def dynamics(self) -> FollowerDynamics:
        return self.backends.dynamics

    @property
    def position_noise_m(self) -> float:
        return self.backends.position_noise_m

    @property
    def heading_noise_rad(self) -> float:
        return self.backends.heading_noise_rad

    @property
    def frames(self) -> RealtimeFrameSource | None:
        return self.backends.frames

    @property
    def camera(self) -> Rig | None:
        return self.backends.camera

    @property
    def obstacles(self) -> tuple[Obstacle, ...]:
        return self.backends.obstacles

    # -- the warm-up's (app.live.warmup.Warmable) ----------------------------------------
    @property
    def ready(self) -> bool:
        """The team's start-up is over: every follower's pose is known (always, with truth feedback)."""
        return self._world.ready

    def throwaway(self, store: ParamsStore, camera: Rig | None, obstacles: tuple[Obstacle, ...]) -> ServiceLoop:
        """A loop like this one (rate, seed, dynamics) on a simulated world of its own, ``camera``'s
        or the truth's: what the warm-up steps with nobody watching and nothing sent to any robot."""
        return ServiceLoop(store, self.backends.simulated(camera, obstacles), rate_hz=self.rate_hz)

    def solver(self, params: Params) -> str:
        return self._safety_settings(params).solver

    # -- wiring ---------------------------------------------------------------------------
    def subscribe(self, fn: Callable[[TickState], None]) -> None:
        self._subscribers.append(fn)

    def stop(self) -> None:
        self._stop.set()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    # -- world ----------------------------------------------------------------------------
    def _make_world(self, params: Params) -> _World:
        made = self.backends.make(params.n_followers, self._resets)
        n = made.team.state.n
        memory = TeamMemory.start(made.start_p, params.slots) if made.start_p is not None \
            else TeamMemory.placeholder(n, params.slots)  # eq. 33 runs once the camera knows the poses
        self.t = 0.0
        self._nav = (math.nan, 1.0)
        self._switch_k = 0
        return _World(made.team, made.feedback, memory, ready=made.start_p is not None, last_cmd=np.zeros((n, 2)),
                      err_norm=np.zeros(n))

    def _safety_settings(self, params: Params) -> SafetySettings:
        if self._safety is None or self._safety.min_distance_m != params.safety_distance_m:
            self._safety = SafetySettings.for_distance(params.safety_distance_m)
        return self._safety

    def _leader_twist(self, params: Params, known: FloatArray, err_norm: FloatArray, tracked: np.ndarray,
                      slots: FloatArray) -> tuple[float, float]:
        if self._mode[0] != params.leader_mode:
            self._mode = (params.leader_mode, self.t)
        v, w = params.leader_speed_mps, math.radians(params.leader_turn_deg_s)
        self._nav_out = None
        if params.leader_mode == "goal":
            if params.goal is None:
                return 0.0, 0.0
            goal = goal_in_leader_frame(params.goal, self._world.team.state.leader)
            team_err = float(err_norm[tracked].max()) if tracked.any() else 0.0
            nav = NavSettings(speed_mps=max(abs(v), 0.01))
            out = navigate(goal, known, team_err, self._nav[0], self._nav[1], slots, params.min_scale, self.dt, nav)
            self._nav = (out.heading, out.scale)
            self._nav_out = out
            return out.twist
        self._nav = (math.nan, min(1.0, self._nav[1] + NavSettings.scale_rate * self.dt))  # grows back in other modes
        if params.leader_mode == "stop":
            return 0.0, 0.0
        if params.leader_mode == "straight":
            return v, 0.0
        if params.leader_mode == "circle":
            return v, w
        profile = Eq39Profile(speed_mps=v, k1_rps=w)
        return profile.twist(self.t - self._mode[1])

    def _over_latency(self, p: FloatArray, a: FloatArray, observed_at: float, twist: tuple[float, float],
                      now: float | None = None) -> tuple[FloatArray, FloatArray]:
        """A real rig's measured latency bridged (core.control.prediction): the observation is as
        old as its frame (arrival to now; older when the camera was late), and this tick's command
        acts half a round trip after it is written (the link's measured RTT). Over the ticks since
        the frame the followers applied the commands sent in them; after, they hold the last one."""
        now = time.monotonic() if now is None else now
        since = max(0.0, now - observed_at) if np.isfinite(observed_at) else 0.0
        past = min(int(round(since / self.dt)), len(self._sent))
        ahead = int(round((self._world.team.radio_delay_s() or 0.0) / self.dt))
        history = list(self._sent)[len(self._sent) - past:]
        last = self._sent[-1][0] if self._sent else np.zeros((len(a), 2))
        commands = [c for c, _ in history] + [last] * ahead
        twists = [t for _, t in history] + [twist] * ahead
        if not commands or any(c.shape != (len(a), 2) for c in commands):
            return p, a
        return predict_poses(p, a, np.array(commands), np.array(twists), self.dt)

    def _leader_motion(self, twist: tuple[float, float]) -> tuple[tuple[float, float], str]:
        """The leader's (v, w) for eq. 5's compensation: what its base measured (its odometry:
        /odom, or a serial base's encoders) while that is fresh, else the commanded twist (and
        the source says why); the commanded one when there is no leader base."""
        base = self._world.team.leader_link
        if base is None:
            return twist, "command"
        if base.lost:
            return twist, "command (no fresh odometry)"
        v, w = base.measured()
        measured = (float(v[0]), float(w[0]))
        if not (math.isfinite(measured[0]) and math.isfinite(measured[1])):
            return twist, "command (no fresh odometry)"
        return measured, "odometry"

    def _robots(self) -> tuple[int, ...] | None:
        """An arena leader's: the fleet's robot index of each follower it drives (None elsewhere)."""
        return self.backends.robots()

    def _name(self, i: int) -> str:
        """Follower ``i``'s one name for people (app.keys.follower_name: "R3 (F1)" in an arena)."""
        robots = self._robots()
        return follower_name(i, robots if robots is not None and i < len(robots) else None)

    def _leader_waits(self, params: Params, tracked: np.ndarray) -> str:
        """Why the leader stands still this tick ('' when it may drive): STOP, or a release that waits
        until every follower is tracked again (``Params.leader_hold``; the loop clears it then)."""
        if params.stop:
            return "STOP"
        if not params.leader_hold:
            return ""
        lost = np.nonzero(~tracked)[0]
        if not self._world.ready:
            return "the team's start-up"
        if len(lost) == 0:
            # the team is whole again: the leader resumes, unless a STOP came in since this tick read
            # the parameters (decided on what is in force now, in one step: never half undo a STOP)
            self.store.change("loop", lambda now: {"leader_hold": False} if now.leader_hold and not now.stop else {})
            return ""
        return "waiting for " + ", ".join(self._name(int(i)) for i in lost) + " to be tracked"

    # -- one tick -------------------------------------------------------------------------
    def tick(self) -> TickState:
        stage: dict[str, float] = dict(self._publish_ms)
        t0 = time.perf_counter()
        params = self.store.get()
        if params.reset_requests != self._resets or params.n_followers != self._world.team.state.n:
            self._resets = params.reset_requests
            self._world = self._make_world(params)
            self._mode = ("", 0.0)
        world = self._world
        while self._switch_k < len(self.switches) and world.ready and due(self.t, self.switches[self._switch_k][0], self.dt):
            slots = self.switches[self._switch_k][1]
            self._switch_k += 1
            if slots.shape[0] == params.n_followers:
                params, _ = self.store.update("scenario", slots=slots)
        if self.fault and not params.stop:  # the operator saw the fault and released STOP
            self.fault = ""
        advance = not params.paused or params.step_requests != self._steps_done
        self._steps_done = params.step_requests

        if advance or world.last_obs is None:
            obs = world.feedback.observe(self.dt, world.last_cmd, world.err_norm)
            fresh = obs is not world.last_obs  # a camera with no new frame hands back the last observation
            world.last_obs = obs
        else:
            obs = world.last_obs  # paused: the world is frozen, so is what the camera sees
            fresh = False
        stage.update(obs.stage_ms)
        p = np.where(np.isfinite(obs.p), obs.p, 0.0)
        a = np.where(np.isfinite(obs.a), obs.a, math.pi / 2)
        tracked = np.asarray(obs.tracked, dtype=bool)
        t1 = time.perf_counter()
        stage["observe"] = (t1 - t0) * 1e3

        if obs.ready and not world.ready:  # the pipeline knows every pose: eq. 33 on its estimates
            world.ready = True
            world.memory = TeamMemory.start(p, params.slots)
            self._mode = ("", self.t)
        known = obs.obstacles if obs.obstacles is not None else np.zeros((0, 2))
        answering = np.asarray(world.team.answering(), dtype=bool)
        tracked = tracked & answering  # a robot whose link does not answer is not one we may command
        waiting = self._leader_waits(params, tracked)
        if waiting or not (advance and world.ready):  # STOP stops the leader too (simulated, real base, arena)
            twist = (0.0, 0.0)
            self._mode = (self._mode[0], self._mode[1] + (self.dt if advance else 0.0))  # a profile's clock waits too
        else:
            twist = self._leader_twist(params, known, world.err_norm, tracked, params.slots)
        motion, source = self._leader_motion(twist)  # eq. 5 compensates what the leader does, when it is measured
        if source != self.leader_motion[1] and "odometry" in (source, self.leader_motion[1]):  # it came, or went stale
            (log.info if source == "odometry" else log.warning)("loop: eq. 5 compensates the leader's %s", source)
        self.leader_motion = (motion, source)
        out, step, safety, p, a = self._commands(params, obs, p, a, tracked, answering, known, motion, advance)
        world.last_cmd = np.column_stack([out.commands.v, out.commands.w])
        self._sent.append((world.last_cmd, motion))
        t2 = time.perf_counter()
        stage["control"] = (t2 - t1) * 1e3

        world.team.send(dataclasses.replace(out.commands, observed_at=obs.observed_at))
        sent_at = time.monotonic()
        t3 = time.perf_counter()
        stage["link"] = (t3 - t2) * 1e3
        # what only the page needs, once the commands are on their way: the limits that bound
        # them, and eq. 21's V per follower with its slope over the last RATE_WINDOW_S
        flags = step_limits(step, params.gains) if step is not None \
            else np.zeros(params.n_followers, dtype=np.int64)
        if advance:
            world.v_hist.append((self.t, out.v_lyap))
            while world.v_hist and world.v_hist[0][0] < self.t - RATE_WINDOW_S:
                world.v_hist.popleft()
        v_rate = lyapunov_rate([h[0] for h in world.v_hist], [h[1] for h in world.v_hist]) \
            if len(world.v_hist) >= 2 else np.zeros(len(a))
        scan = world.feedback.scan_after()  # after the commands: off the frame's way to the robots
        if scan is not None or world.feedback.scan_pending:  # a scan's second half, or its first
            stage["scan"] = (time.perf_counter() - t3) * 1e3

        p_true, a_true = world.team.truth()
        state = TickState(
            tick=self.tick_count, t=self.t, leader=world.team.state.leader.copy(), leader_twist=twist,
            followers_world=world.team.state.followers.copy(), p_est=obs.p, a_est=obs.a, tracked=tracked,
            p_true=p_true, a_true=a_true, p_d=world.memory.slots.p_d.copy(), slot_targets=params.slots.copy(),
            assignment=world.memory.assignment.copy(),
            commands=np.column_stack([out.commands.v, out.commands.w]), a_err=out.a_err,
            v_lyap=out.v_lyap, gains=params.gains, params_version=params.version,
            stopped=params.stop, paused=params.paused and not advance,
            link_state=world.team.link_state + (" · eq. 5 on the commanded twist" if source.startswith("command (")
                                                else ""),
            rate_hz=self.achieved_rate_hz, stage_ms=stage, phase=obs.phase, probing=obs.probing,
            a_raw=obs.a_raw, frame=obs.frame, windows=obs.windows, hues_deg=obs.hues_deg,
            link_detail=world.team.link_detail(), fault=self.fault, camera_state=obs.camera_state,
            safety=safety_text(safety, params.safety, self._name), safety_changed=None if safety is None else safety.changed,
            min_distance_m=(safety.min_distance_m if safety is not None  # the filter measured it already
                            else team_min_distance(p[tracked]) if tracked.any() else float("nan")),
            safety_active=None if safety is None else safety.active, obstacles=known, scan=scan,
            goal=params.goal if params.leader_mode == "goal" else None,
            heading=self._nav_out.heading if self._nav_out is not None else float("nan"),
            formation_scale=self._nav[1], goal_reached=self._nav_out is not None and self._nav_out.reached,
            limits=flags, v_rate=v_rate, leader_waits=waiting, latency_ms=(sent_at - obs.observed_at) * 1e3,
            fresh=fresh, robots=self._robots(),
        )
        if advance:
            world.team.advance(twist, self.dt, self.t)
            self.t += self.dt
        self.tick_count += 1
        self.last = state
        self._publish(state)
        return state

    def _commands(self, params: Params, obs: Observation, p: FloatArray, a: FloatArray, tracked: BoolArray,
                  answering: BoolArray, known: FloatArray, twist: tuple[float, float], advance: bool,
                  ) -> tuple[ControlOutput, TeamStep | None, SafetyResult | None, FloatArray, FloatArray]:
        """This tick's commands: the start-up's manoeuvres, or the team's control step
        (core.control.step); zero for a robot that does not answer. Also where each follower
        is taken to be (predicted over a real rig's latency). The control step, when one was taken
        (None during the start-up): step_limits names its limit flags once the commands are sent."""
        world = self._world
        settings = self._safety_settings(params) if params.safety else None
        safety = None
        step: TeamStep | None = None
        if obs.manoeuvre is not None:  # start-up (paper §3.1-3.2): the pipeline drives, the leader waits
            if world.ready:
                world.memory = world.memory.slots_on(p, params.slots, self._nav[1], self.dt, keep_out_m(settings),
                                                     advance)
            move = advance and not params.stop
            manoeuvre = obs.manoeuvre * answering[:, None] if move else np.zeros((params.n_followers, 2))
            out = ControlOutput.idle(manoeuvre)
            world.err_norm = np.linalg.norm(world.memory.slots.p_d - p, axis=1)
        else:
            acting = None
            if advance and world.team.radio_delay_s() is not None:  # a real rig: each follower where it will be
                acting = self._over_latency(p, a, obs.observed_at, twist)  # when this acts
            step = team_step(world.memory, p, a, tracked, params.slots, twist, params.gains, self.dt,
                             active=tracked & (not params.stop) & advance, obstacles=known, safety=settings,
                             filter_now=not params.stop, scale=self._nav[1], advance=advance and world.ready,
                             acting=acting, limits=False)
            world.memory, out, safety, world.err_norm = step.memory, step.control, step.safety, step.err_norm
            if acting is not None:
                p, a = acting
        if world.team.link_lost:  # nobody answers: no command but zero until the robots do
            out = ControlOutput.idle(np.zeros((len(a), 2)))
            world.memory = world.memory.halted()
        elif not answering.all():  # and a robot that does not answer gets zero until it does
            out = dataclasses.replace(out, commands=Commands(np.where(answering, out.commands.v, 0.0),
                                                             np.where(answering, out.commands.w, 0.0)))
        return out, step, safety, p, a

    def _publish(self, state: TickState) -> None:
        """Every subscriber sees the tick; one that fails is logged and the loop goes on."""
        publish: dict[str, float] = {}
        for fn in self._subscribers:
            t_pub = time.perf_counter()
            try:
                fn(state)
            except Exception:  # a broken view must not stop the robots' loop
                log.exception("subscriber failed")
            publish[f"publish:{getattr(fn, '__qualname__', 'fn')}"] = (time.perf_counter() - t_pub) * 1e3
        self._publish_ms = publish  # shown with the next tick: a published state is never changed

    def _timed_tick(self, start: float, window: deque[float]) -> None:
        """One tick (a fault stops the robots, never the loop), and the rate over the last ticks."""
        try:
            self.tick()
        except Exception as exc:  # noqa: BLE001 - the robots must stop, the service must live
            self._on_fault(exc)
        if self.cpu is not None and self.tick_count % max(1, round(self.rate_hz)) == 0:
            self.cpu.keep_off()  # once a second, after the tick's commands: threads made since, a new page
        if window:
            self._longest_gap_s = max(self._longest_gap_s, start - window[-1])
        window.append(start)
        if len(window) >= 2 and window[-1] > window[0]:
            self.achieved_rate_hz = (len(window) - 1) / (window[-1] - window[0])

    def _ask_realtime(self) -> None:
        # with the loop on real-time scheduling, a thread holding the GIL is what is left (app.realtime)
        sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
        why = make_realtime()
        camera = self.frames
        camera_why = camera.make_realtime() if camera is not None else ""
        self.priority = scheduling() if not why else f"normal (real-time refused: {why})"
        if why or camera_why:
            log.warning("loop: --realtime: %s", why or f"the camera's thread: {camera_why}")
        else:
            log.info("loop: real-time scheduling for the loop%s", " and the camera" if camera is not None else "")

    def _run_on_frames(self, frames: RealtimeFrameSource) -> None:
        """Frame-triggered ticks: each starts as soon as a new frame arrives, so no frame waits for
        the loop's schedule. No frame within ``LATE_FRAME_PERIODS`` periods of the configured rate
        is a late camera: the tick runs anyway, on the newest estimates, and the stale-frame rule
        (app.backends.feedback) stops the robots once the frame is too old. Each tick's dt is the time
        since the one before (clamped to a sane range), as the real rig's odometry needs."""
        nominal = self.dt
        count = frames.wait_newer(-1, 0.0)  # the newest frame's number now
        last = time.monotonic()
        window: deque[float] = deque(maxlen=61)
        try:
            while not self._stop.is_set():
                newest = frames.wait_newer(count, LATE_FRAME_PERIODS * nominal)
                if newest <= count:
                    self.late_frames += 1
                count = newest
                if self._stop.is_set():
                    break
                start = time.monotonic()
                self.dt = min(max(start - last, DT_RANGE[0] * nominal), DT_RANGE[1] * nominal)
                last = start
                self._timed_tick(start, window)
        finally:
            self.dt = nominal
            self.halt_followers()
            self._world.team.close()

    def _on_fault(self, exc: Exception) -> None:
        """An exception inside a tick: every follower to zero at once, STOP engaged (the
        operator sees why and releases it), the loop goes on observing."""
        self.halt_followers()  # first: the robots
        self.fault = f"{type(exc).__name__}: {exc}"[:200]
        if not self.store.get().stop:
            self.store.update("loop", stop=True)
        self.faults += 1
        if self.faults <= 3 or self.faults % 100 == 0:
            log.exception("loop fault %d; every follower stopped", self.faults)

    def halt_followers(self) -> None:
        """Command every follower to zero now (used on stop and on errors)."""
        n = self._world.team.state.n
        self._world.team.send(Commands.zeros(n))
        self._world.memory = self._world.memory.halted()
        self._world.last_cmd = np.zeros((n, 2))

    def close_team(self) -> None:
        """For a loop that never ran: every follower to zero and the team's link closed (what
        the end of :meth:`run` does)."""
        self.halt_followers()
        self._world.team.close()

    # -- pacing ---------------------------------------------------------------------------
    def take_longest_gap(self) -> float:
        """The longest time between two tick starts since the last call, in seconds (a stall
        shows here; the loop catches up on what it missed unless it was more than CATCH_UP_S late)."""
        gap, self._longest_gap_s = self._longest_gap_s, 0.0
        return gap

    def run(self) -> None:
        """Tick until stop(): on a camera's frames when the loop has one (``frames``), else at the
        configured rate. Always leaves the followers at zero. Every kernel it can reach is compiled
        and warmed first, before its clock starts (app.live.warmup)."""
        warm_up(self)
        compiled_at_start = compiled()
        if self.cpu is not None:  # one line, as the warm-up's: the operator starts a browser off that CPU
            why = self.cpu.take()
            print(f"omniformation: no CPU kept for the loop ({why})" if why else
                  f"omniformation: CPU {self.cpu.cpu} kept for the loop's thread; the service's other threads and its"
                  f" page run on {','.join(map(str, sorted(self.cpu.others)))}", flush=True)
        try:
            self._paced()
        finally:
            if self.cpu is not None:
                self.cpu.release()
            late = compiled() - compiled_at_start
            if late:  # a kernel the warm-up did not reach: its first use stalled a tick (name it in app.live.warmup)
                log.warning("loop: %d kernel(s) compiled while the loop's clock ran", late)

    def _paced(self) -> None:
        if self.realtime:
            self._ask_realtime()
        if self.frames is not None:
            self._run_on_frames(self.frames)
            return
        next_deadline = time.monotonic()
        window: deque[float] = deque(maxlen=61)  # tick start times of the last 60 ticks
        late_limit = max(CATCH_UP_S, CATCH_UP_TICKS * self.dt)
        try:
            while not self._stop.is_set():
                self._timed_tick(time.monotonic(), window)
                now = time.monotonic()
                next_deadline, wait_s, skipped = next_tick(next_deadline, now, self.dt, late_limit)
                if skipped:
                    self.ticks_dropped += skipped
                    log.warning("loop: over %.0f ms behind its schedule, %d ticks (%.0f ms) skipped", late_limit * 1e3,
                                skipped, skipped * self.dt * 1e3)
                elif wait_s > 0:
                    self._stop.wait(wait_s)
        finally:
            self.halt_followers()
            self._world.team.close()
