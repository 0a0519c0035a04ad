"""Closed loop with vision: simulator → synthetic frame → pipeline → controller → simulator.

The start-up manoeuvres of §3.1–3.2 take simulated time, as on the real robots: the leader
stands still until the pipeline is ready, then its profile starts (scenario time 0). Log
rows before that have negative time. Disturbances ("stuck", "hidden") use scenario time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from collections.abc import Callable

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.camera.render import Renderer
from core.config import Scenario
from core.control.assignment import assign_slots
from core.control.formation import ControllerState, compute_commands
from core.geometry import heading_world_to_leader, leader_displacement, world_to_leader
from core.sim.run import SimulationLog
from core.sim.team import disturbance_mask, make_team_state, step_team
from core.types import BoolArray, Commands, FloatArray, Image, IntArray
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


def simulate_vision(
    scenario: Scenario,
    rig: CameraConfig,
    gamma: Gamma,
    settings: PipelineSettings = PipelineSettings(),
    max_startup_s: float = 60.0,
    on_frame: Callable[[int, Image], None] | None = None,
) -> VisionLog:
    """Run ``scenario`` with the controller fed by the vision pipeline on rendered frames.

    ``on_frame(k, frame)`` sees every frame (row k of the log), e.g. to record it;
    ``np.asarray(frame)`` renders the whole of it."""
    if rig.model is None:
        raise ValueError(f"{rig.source}: a vision simulation needs the rig's [model]")
    dt = 1.0 / scenario.rate_hz
    n = scenario.n
    rng = np.random.default_rng(scenario.seed)
    renderer = Renderer(rig.model, rig.render)
    pipeline = VisionPipeline(n, gamma, rig.working_area, rig.detect, (rig.model.width, rig.model.height),
                              np.random.default_rng(scenario.seed + 1), settings)
    state = make_team_state(scenario.initial_p, scenario.initial_a)
    ctrl_state = ControllerState.initial(n)
    p_d = np.zeros((n, 2))
    assignment = np.arange(n)

    rows: dict[str, list[object]] = {k: [] for k in (
        "t", "leader", "twist", "fw", "p", "a", "pm", "am", "pd", "cmd", "aerr", "tracked", "meas", "phase", "win",
        "hue")}
    prev_leader = state.leader.copy()
    last_cmd = np.zeros((n, 2))
    err_norm = np.zeros(n)
    t_ready: float | None = None
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
        hidden = disturbance_mask(scenario.disturbances, n, t_scn, "hidden")[0] if t_ready is not None else None
        # pixels are made only where the pipeline looks (bit for bit the whole frame's there)
        frame = renderer.frame(state.leader, np.column_stack([p_true, a_true]), t_wall, rng, hidden=hidden)
        if on_frame is not None:
            on_frame(k, frame)
        odo = leader_displacement(prev_leader, state.leader)
        out = pipeline.step(frame, dt, odo, last_cmd, err_norm)
        prev_leader = state.leader.copy()

        if out.manoeuvre is not None:
            v_l = w_l = 0.0
            v_cmd, w_cmd = out.manoeuvre[:, 0], out.manoeuvre[:, 1]
            a_err = np.zeros(n)
        else:
            if t_ready is None:
                t_ready = t_wall
                t_scn = 0.0
                known = np.where(np.isfinite(out.positions), out.positions, 0.0)
                assignment = assign_slots(known, scenario.slots)  # eq. 33 on the first estimates
                p_d = np.ascontiguousarray(scenario.slots[assignment])
            v_l, w_l = (float(x) for x in scenario.leader.twist(t_scn))
            pos = np.where(np.isfinite(out.positions), out.positions, 0.0)
            head = np.where(np.isfinite(out.headings), out.headings, math.pi / 2)
            c = compute_commands(pos, head, p_d, np.zeros((n, 2)), v_l, w_l, scenario.gains, ctrl_state, dt,
                                 active=out.tracked)
            ctrl_state = c.state
            v_cmd, w_cmd = c.commands.v, c.commands.w
            a_err = c.a_err
            err_norm = np.hypot(p_d[:, 0] - pos[:, 0], p_d[:, 1] - pos[:, 1])

        rows["t"].append(t_wall)
        rows["leader"].append(state.leader.copy())
        rows["twist"].append((v_l, w_l))
        rows["fw"].append(state.followers.copy())
        rows["p"].append(p_true)
        rows["a"].append(a_true)
        rows["pm"].append(out.positions)
        rows["am"].append(out.headings)
        rows["pd"].append(p_d.copy() if t_ready is not None else np.full((n, 2), np.nan))  # no target yet
        last_cmd = np.column_stack([v_cmd, w_cmd])
        rows["cmd"].append(last_cmd)
        rows["aerr"].append(a_err)
        rows["tracked"].append(out.tracked)
        rows["meas"].append(out.heading_measured)
        rows["phase"].append(out.phase)
        rows["win"].append(out.windows)
        rows["hue"].append(out.hues_deg)

        state = step_team(state, Commands(np.asarray(v_cmd), np.asarray(w_cmd)), (v_l, w_l), dt,
                          t_scn if t_ready is not None else -1.0, rng, scenario.dynamics,
                          scenario.disturbances if t_ready is not None else ())
        k += 1

    assert t_ready is not None
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
        assignment=np.asarray(assignment),
    )
    return VisionLog(log, np.array(rows["tracked"]), np.array(rows["meas"]), tuple(str(ph) for ph in rows["phase"]), t_ready,
                     np.array(rows["win"], dtype=np.int64), np.array(rows["hue"]))
