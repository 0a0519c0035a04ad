"""A recorded session again (`omniformation rerun FILE --out NEW.mcap`, app.cli.sessions), with other settings.

Two jobs, both written as a new recording (replay it, report it) and summed up per follower:

* **The frames again** (``--pipeline-config``, or nothing): the recorded camera frames go
  through the vision pipeline once more. It starts tracking (§3.3) from the recorded state
  at the first frame after the recorded start-up — each follower's window and heading —
  and then steps frame by frame with the recorded leader odometry (eq. 38) and commands
  (eq. 34–37), as the live loop did. It prints how far the new estimates are from the
  recorded ones (RMS per follower), and from the truth when the session was simulated.
* **The team again** (``--gains``, simulated sessions only): the scenario the session ran
  is simulated anew from the same start with the new gains (through the camera if the
  session was), and the settling time and steady error are compared with the recording's.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from collections.abc import Callable

import cv2
import numpy as np

from app.contracts import Rig
from app.files import SYNTHETIC_CALIBRATED, UserError
from app.recording.reader import Recording, params_from_recording
from app.recording.schema import json_floats, tick_from_payload
from app.recording.writer import Recorder
from core.camera.config import CameraConfig, parse_camera
from core.config import ConfigError, parse_scenario
from core.geometry import leader_displacement, wrap_angle
from core.types import GAIN_BOUNDS, Gains
from core.vision.pipeline import PipelineSettings, VisionPipeline

Progress = Callable[[int, int], None]


def parse_gains(text: str, base: Gains) -> Gains:
    """``k_f1=0.12,k_w2=2`` over ``base``; one-line UserError naming the bad part."""
    changes: dict[str, float] = {}
    if not text.replace(",", "").strip():
        raise UserError(f"--gains {text!r}: give NAME=NUMBER pairs, e.g. k_f1=0.12,k_w2=2 (NAME one of"
                        f" {', '.join(GAIN_BOUNDS)})")
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep or name not in GAIN_BOUNDS:
            raise UserError(f"--gains {part!r}: must be NAME=NUMBER with NAME one of {', '.join(GAIN_BOUNDS)}")
        try:
            changes[name] = float(value)
        except ValueError:
            raise UserError(f"--gains {part!r}: {value.strip()!r} is not a number") from None
    try:
        return base.replace(**changes)
    except ValueError as exc:
        raise UserError(f"--gains: {exc}") from None


def recorded_calibration(rec: Recording, override: Path | None) -> CameraConfig:
    """The Γ the session used (kept in its metadata), or the one given, or the built-in one."""
    from app.files import load_calibration, require_gamma

    if override is None and "calibration_toml" in rec.metadata:
        try:
            cfg = parse_camera(rec.metadata["calibration_toml"], f"{rec.path.name} (its calibration)")
        except ConfigError as exc:
            raise UserError(str(exc)) from None
        require_gamma(cfg)
        return cfg
    return load_calibration(override or SYNTHETIC_CALIBRATED)[0]


@dataclass
class FrameRerun:
    t: np.ndarray  # (F,) frame times
    ticks: list[int]  # the recorded tick index of each frame
    p_new: np.ndarray  # (F, n, 2)
    a_new: np.ndarray  # (F, n)
    tracked_new: np.ndarray  # (F, n)
    windows_new: np.ndarray  # (F, n, 4)
    p_old: np.ndarray
    a_old: np.ndarray
    tracked_old: np.ndarray
    p_true: np.ndarray
    a_true: np.ndarray
    resumed: np.ndarray  # (n,) followers found again at the first frame


def _decode(jpeg: bytes) -> np.ndarray:
    """A recorded JPEG frame; one that does not decode is one line."""
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    if img is None:
        raise UserError("a recorded camera frame is not a readable JPEG")
    return np.asarray(img)


def rerun_frames(rec: Recording, camera: CameraConfig, settings: PipelineSettings,
                 progress: Progress | None = None) -> FrameRerun:
    if not len(rec.frames):
        raise UserError(f"{rec.path.name}: has no camera frames to re-run (recorded with --frames-hz 0, or"
                        " without the camera)")
    t_ticks = rec.t
    phases = [tk.get("phase", "truth") for tk in rec.ticks]
    tracking = [k for k, ph in enumerate(phases) if ph == "tracking"]
    if not tracking:
        raise UserError(f"{rec.path.name}: the vision pipeline never reached formation tracking in this recording")
    t_start = float(t_ticks[tracking[0]])
    chosen = [int(j) for j in np.nonzero(rec.frame_t >= t_start - 1e-9)[0]]  # frames are read one at a time
    if len(chosen) < 2:
        raise UserError(f"{rec.path.name}: fewer than two camera frames after the start-up: nothing to re-run")
    frame_times = rec.frame_t[chosen]
    index = [int(np.clip(np.searchsorted(t_ticks, t + 1e-6) - 1, 0, len(t_ticks) - 1)) for t in frame_times]
    assert camera.gamma is not None
    n = len(rec.ticks[0]["a_est"])
    first = _decode(rec.frames[chosen[0]][1])
    pipeline = VisionPipeline(n, camera.gamma, camera.working_area, camera.detect, (first.shape[1], first.shape[0]),
                              np.random.default_rng(0), settings)
    tk0 = tick_from_payload(rec.ticks[index[0]])
    assert tk0.windows is not None, "simulate --record and run keep the CAMSHIFT windows"
    resumed = pipeline.resume_tracking(first, tk0.windows, tk0.a_est)
    F = len(chosen)
    out = FrameRerun(np.array(frame_times), index, np.full((F, n, 2), np.nan), np.full((F, n), np.nan),
                     np.zeros((F, n), bool), np.zeros((F, n, 4), np.int64), np.full((F, n, 2), np.nan),
                     np.full((F, n), np.nan), np.zeros((F, n), bool), np.full((F, n, 2), np.nan),
                     np.full((F, n), np.nan), resumed)
    prev, before = index[0], tk0
    for j, (jf, k) in enumerate(zip(chosen, index)):
        tk = tick_from_payload(rec.ticks[k])
        if j == 0:
            positions = pipeline.positions.copy()
            headings = pipeline.headings.headings
            tracked, windows = resumed.copy(), tk0.windows
        else:
            frame = _decode(rec.frames[jf][1])
            span = rec.ticks[prev + 1:k + 1] or [rec.ticks[k]]
            cmd = np.nanmean([json_floats(s["commands"]).reshape(n, 2) for s in span], axis=0)
            err = np.linalg.norm(before.p_d - before.p_est, axis=1)
            odo = leader_displacement(before.leader, tk.leader)
            res = pipeline.step(frame, float(t_ticks[k] - t_ticks[prev]), odo, np.nan_to_num(cmd), np.nan_to_num(err))
            positions, headings, tracked, windows = res.positions, res.headings, res.tracked, res.windows
        out.p_new[j], out.a_new[j], out.tracked_new[j], out.windows_new[j] = positions, headings, tracked, windows
        out.p_old[j], out.a_old[j], out.tracked_old[j] = tk.p_est, tk.a_est, tk.tracked
        out.p_true[j], out.a_true[j] = tk.p_true, tk.a_true
        before = tk
        prev = k
        if progress is not None:
            progress(j + 1, F)
    return out


def _rms(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x**2))) if x.size else math.nan


def frame_summary(r: FrameRerun) -> list[dict[str, float]]:
    """Per follower: new vs recorded estimates, and both vs the truth when it was recorded."""
    rows = []
    both = r.tracked_new & r.tracked_old
    for i in range(r.p_new.shape[1]):
        m = both[:, i]
        dp = np.linalg.norm(r.p_new[m, i] - r.p_old[m, i], axis=-1)
        da = np.degrees(np.asarray(wrap_angle(r.a_new[m, i] - r.a_old[m, i])))
        row = {"follower": i + 1, "position_change_rms_cm": _rms(dp) * 100, "heading_change_rms_deg": _rms(da),
               "tracked_new_pct": float(r.tracked_new[:, i].mean() * 100),
               "tracked_recorded_pct": float(r.tracked_old[:, i].mean() * 100)}
        if np.isfinite(r.p_true[:, i]).any():
            for name, p, a, tr in (("recorded", r.p_old, r.a_old, r.tracked_old), ("new", r.p_new, r.a_new, r.tracked_new)):
                sel = tr[:, i]
                row[f"{name}_error_rms_cm"] = _rms(np.linalg.norm(p[sel, i] - r.p_true[sel, i], axis=-1)) * 100
                row[f"{name}_heading_error_rms_deg"] = _rms(np.degrees(np.asarray(wrap_angle(a[sel, i] - r.a_true[sel, i]))))
        rows.append(row)
    return rows


def write_frame_rerun(rec: Recording, r: FrameRerun, path: Path, note: dict[str, str]) -> int:
    """The re-run as a recording: one tick per frame, the new estimates, the same frames."""
    start_ns = int(rec.metadata.get("start_ns", "0") or 0)
    meta = {k: v for k, v in rec.metadata.items() if k != "start_ns"} | note
    out = Recorder(path, meta, params_from_recording(rec), frame_rate_hz=0.0, start_ns=start_ns, lossless=True)
    frame_at = {float(t): j for j, t in enumerate(rec.frame_t)}
    try:
        for j, k in enumerate(r.ticks):
            state = dataclasses.replace(tick_from_payload(rec.ticks[k]), tick=j, p_est=r.p_new[j], a_est=r.a_new[j],
                                        a_raw=r.a_new[j], tracked=r.tracked_new[j], windows=r.windows_new[j],
                                        stage_ms={})
            out.on_tick(state)
            out.add_jpeg(float(r.t[j]), rec.frames[frame_at[float(r.t[j])]][1])
    finally:
        out.close()
    return len(r.ticks)


def resimulate(rec: Recording, gains: Gains, settings: PipelineSettings, out_path: Path,
               camera: CameraConfig | None) -> Path:
    """The session's scenario from the same start with new gains (and pipeline settings)."""
    from app.recording.simulated import record_run, run_simulation
    from app.recording.session import session_metadata

    text = rec.metadata.get("scenario_toml")
    if not text:
        raise UserError(f"{rec.path.name}: --gains re-simulates the session's scenario, and this recording has none"
                        " (a live run without --scenario, or a real rig): re-run its frames instead")
    try:
        scenario = parse_scenario(text, f"{rec.path.name} (its scenario)")
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    changes: dict[str, Any] = {"gains": gains}
    for key, cast in (("duration_s", float), ("rate_hz", float), ("seed", int)):
        if key in rec.metadata:
            changes[key] = cast(rec.metadata[key])
    scenario = scenario.replace(**changes)
    sim_camera: Rig | None = None  # through the camera if the session was
    if camera is not None and len(rec.frames):
        from app.files import load_camera, require_gamma
        from app.files import SYNTHETIC_CAMERA

        sim_camera = Rig(load_camera(SYNTHETIC_CAMERA), require_gamma(camera))
    frames_hz = float(rec.metadata.get("frames_hz", "0") or 0) if sim_camera else 0.0
    run = run_simulation(scenario, sim_camera, settings, frames_hz=frames_hz or (1.0 if sim_camera else 0.0))
    meta = session_metadata(scenario.name, None, sim_camera)
    meta.update(scenario_toml=text, duration_s=f"{scenario.duration_s:g}", rate_hz=f"{scenario.rate_hz:g}",
                seed=str(scenario.seed), rerun_of=rec.path.name, gains=json.dumps(gains.as_dict()))
    record_run(run, out_path, meta, frames_hz)
    return out_path
