"""Offline runs: a scenario simulated (with the controller fed by ground truth plus noise,
or by the vision pipeline on rendered frames) and written as the same MCAP a live session
makes. `simulate` and `rerun` both use it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from app.contracts import Rig
from app.tick import TickState
from app.params import Params
from app.recording.writer import Recorder
from core.config import Scenario
from core.sim.run import SimulationLog
from core.sim.profiles import GoalProfile
from core.sim.runner import run_scenario
from core.sim.stepped import SafetyLog
from core.sim.vision_run import VisionLog
from core.vision.freespace import Scan
from core.types import Image
from core.vision.pipeline import PipelineSettings


@dataclass
class SimRun:
    log: SimulationLog
    vision: VisionLog | None = None
    frames: dict[int, bytes] = field(default_factory=dict)  # row -> JPEG, kept for a recording
    safety: SafetyLog | None = None  # the stepped simulator's (obstacles, the filter, a goal, switches)


def run_simulation(scenario: Scenario, camera: Rig | None = None,
                   settings: PipelineSettings = PipelineSettings(), frames_hz: float = 0.0,
                   jpeg_quality: int = 80) -> SimRun:
    """The scenario with ground-truth feedback, or with ``camera`` (a synthetic rig and its Γ)
    through the vision pipeline (core.sim.runner: the run a study makes of it too), keeping
    ``frames_hz`` JPEG frames a second."""
    every = max(1, int(round(scenario.rate_hz / frames_hz))) if frames_hz > 0 else 0
    frames: dict[int, bytes] = {}

    def keep(k: int, frame: Image) -> None:
        if every and k % every == 0:  # only a kept frame is rendered whole
            frames[k] = cv2.imencode(".jpg", np.asarray(frame), [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])[1].tobytes()

    run = run_scenario(scenario, camera[0] if camera else None, camera[1] if camera else None, settings,
                       on_frame=keep if every else None)
    return SimRun(run.log, run.vision, frames, run.safety)


def record_run(run: SimRun, path: Path, metadata: dict[str, str], frames_hz: float) -> int:
    """Write a run as a recording; returns the ticks written."""
    log, vision = run.log, run.vision
    meta = {**metadata, "scenario_start_s": f"{-float(log.t[0]):.6f}"}
    a_raw = None
    if vision is not None:  # the eq. 34-37 measurements, held between them (as the live loop shows them)
        a_raw = vision.heading_measured.copy()
        for k in range(1, len(a_raw)):
            a_raw[k] = np.where(np.isfinite(a_raw[k]), a_raw[k], a_raw[k - 1])
        a_raw = np.where(np.isfinite(a_raw), a_raw, log.a_meas)
    return record_simulation(log, path, meta, tracked=vision.tracked if vision is not None else None,
                             phases=vision.phase if vision is not None else None, frames=run.frames or None,
                             a_raw=a_raw, frame_rate_hz=frames_hz,
                             windows=vision.windows if vision is not None else None,
                             hues_deg=vision.hues_deg if vision is not None else None, safety=run.safety)


def record_simulation(
    log: SimulationLog,
    path: Path,
    metadata: dict[str, str],
    tracked: np.ndarray | None = None,
    phases: tuple[str, ...] | None = None,
    frames: dict[int, bytes] | None = None,
    a_raw: np.ndarray | None = None,
    frame_rate_hz: float = 10.0,
    windows: np.ndarray | None = None,
    hues_deg: np.ndarray | None = None,
    safety: SafetyLog | None = None,
) -> int:
    """Write every row of ``log`` as a tick, and the JPEG frames given (by row); returns the ticks."""
    sc = log.scenario
    n = log.n
    params = Params(gains=sc.gains, slots=sc.slots.copy(), n_followers=n, leader_mode="stop")
    rec = Recorder(path, {**metadata, "frames_hz": f"{frame_rate_hz:g}"}, params, frame_rate_hz=frame_rate_hz, lossless=True,
                   start_ns=0)
    v_lyap = log.v_lyap
    goal = sc.leader.goal if isinstance(sc.leader, GoalProfile) else None
    try:
        for k in range(len(log.t)):
            extra: dict[str, object] = {}
            if safety is not None:
                status = safety.status[k]
                extra = dict(
                    safety="off" if status == "off" else f"on, {'changed' if status == 'filtered' else status}",
                    safety_changed=safety.changed[k], min_distance_m=float(safety.min_distance[k]),
                    obstacles=safety.obstacle_points[k] if safety.obstacle_points else None,
                    goal=goal, formation_scale=float(safety.scale[k]),
                    goal_reached=bool(np.isfinite(safety.goal_reached_s) and log.t[k] >= safety.goal_reached_s),
                    scan=_scan_row(safety, k),
                )
            rec.on_tick(TickState(
                tick=k, t=float(log.t[k]) - float(log.t[0]), leader=log.leader[k],
                leader_twist=(float(log.leader_twist[k, 0]), float(log.leader_twist[k, 1])),
                followers_world=log.followers_world[k], p_est=log.p_meas[k], a_est=log.a_meas[k],
                tracked=tracked[k] if tracked is not None else np.ones(n, dtype=bool),
                p_true=log.p[k], a_true=log.a[k], p_d=log.p_d[k], slot_targets=sc.slots,
                assignment=log.assignment, commands=log.commands[k], a_err=log.a_err[k],
                v_lyap=v_lyap[k], gains=sc.gains, params_version=0, stopped=False, paused=False,
                link_state="simulated", rate_hz=sc.rate_hz, stage_ms={},
                phase=phases[k] if phases is not None else "truth",
                a_raw=a_raw[k] if a_raw is not None else None,
                windows=windows[k] if windows is not None else None,
                hues_deg=hues_deg[k] if hues_deg is not None else None, **extra,  # type: ignore[arg-type]  # TickState's fields, typed there
            ))
            if frames is not None and k in frames:
                rec.add_jpeg(float(log.t[k]) - float(log.t[0]), frames[k])
    finally:
        rec.close()
    return len(log.t)


def _scan_row(safety: SafetyLog, k: int) -> Scan | None:
    """Row k of a stepped run's scans as a Scan (None where none was taken: the start-up, no obstacles)."""
    if safety.scan_ranges is None or safety.scan_bearings is None or np.isnan(safety.scan_ranges[k]).all():
        return None
    ranges = safety.scan_ranges[k]
    return Scan(safety.scan_bearings, ranges, np.full_like(ranges, np.nan), np.zeros(len(ranges), dtype=bool), 0.0)
