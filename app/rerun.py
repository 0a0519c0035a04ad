"""`omniformation rerun FILE --out NEW.mcap`: a recorded session again, with other settings.

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
from typing import Any, Callable

import cv2
import numpy as np

from app.paths import SYNTHETIC_CALIBRATED, UserError, display_path
from app.recorder import (Recorder, Recording, json_floats, params_from_recording, read_recording,
                          tick_from_payload)
from core.camera.config import CameraConfig, parse_camera
from core.config import ConfigError, parse_scenario
from core.geometry import leader_displacement, wrap_angle
from core.types import GAIN_BOUNDS, Gains
from core.vision.pipeline import PipelineSettings, VisionPipeline

Progress = Callable[[int, int], None]


def parse_gains(text: str, base: Gains) -> Gains:
    """``k_f1=0.12,k_w2=2`` over ``base``; one-line UserError naming the bad part."""
    changes: dict[str, float] = {}
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
    from app.camera_files import load_calibration, require_gamma

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


def rerun_frames(rec: Recording, camera: CameraConfig, settings: PipelineSettings,
                 progress: Progress | None = None) -> FrameRerun:
    if not rec.frames:
        raise UserError(f"{rec.path.name}: has no camera frames to re-run (recorded with --frames-hz 0, or"
                        " without the camera)")
    t_ticks = rec.t
    phases = [tk.get("phase", "truth") for tk in rec.ticks]
    tracking = [k for k, ph in enumerate(phases) if ph == "tracking"]
    if not tracking:
        raise UserError(f"{rec.path.name}: the vision pipeline never reached formation tracking in this recording")
    t_start = float(t_ticks[tracking[0]])
    frames = [(t, jpg) for t, jpg in rec.frames if t >= t_start - 1e-9]
    if len(frames) < 2:
        raise UserError(f"{rec.path.name}: fewer than two camera frames after the start-up: nothing to re-run")
    index = [int(np.clip(np.searchsorted(t_ticks, t + 1e-6) - 1, 0, len(t_ticks) - 1)) for t, _ in frames]
    assert camera.gamma is not None
    n = len(rec.ticks[0]["a_est"])
    first = cv2.imdecode(np.frombuffer(frames[0][1], np.uint8), cv2.IMREAD_COLOR)
    pipeline = VisionPipeline(n, camera.gamma, camera.working_area, camera.detect, (first.shape[1], first.shape[0]),
                              np.random.default_rng(0), settings)
    tk0 = tick_from_payload(rec.ticks[index[0]])
    assert tk0.windows is not None, "simulate --record and run keep the CAMSHIFT windows"
    resumed = pipeline.resume_tracking(first, tk0.windows, tk0.a_est)
    F = len(frames)
    out = FrameRerun(np.array([t for t, _ in frames]), index, np.full((F, n, 2), np.nan), np.full((F, n), np.nan),
                     np.zeros((F, n), bool), np.zeros((F, n, 4), np.int64), np.full((F, n, 2), np.nan),
                     np.full((F, n), np.nan), np.zeros((F, n), bool), np.full((F, n, 2), np.nan),
                     np.full((F, n), np.nan), resumed)
    prev, before = index[0], tk0
    for j, ((t, jpg), k) in enumerate(zip(frames, index)):
        tk = tick_from_payload(rec.ticks[k])
        if j == 0:
            positions = pipeline.positions.copy()
            headings = pipeline.headings.headings
            tracked, windows = resumed.copy(), tk0.windows
        else:
            frame = cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_COLOR)
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
    out = Recorder(path, meta, params_from_recording(rec), frame_rate_hz=0.0, start_ns=start_ns)
    frames = dict(rec.frames)
    try:
        for j, k in enumerate(r.ticks):
            state = dataclasses.replace(tick_from_payload(rec.ticks[k]), tick=j, p_est=r.p_new[j], a_est=r.a_new[j],
                                        a_raw=r.a_new[j], tracked=r.tracked_new[j], windows=r.windows_new[j],
                                        stage_ms={})
            out.on_tick(state)
            out.add_jpeg(float(r.t[j]), frames[float(r.t[j])])
    finally:
        out.close()
    return len(r.ticks)


def resimulate(rec: Recording, gains: Gains, settings: PipelineSettings, out_path: Path,
               camera: CameraConfig | None) -> Path:
    """The session's scenario from the same start with new gains (and pipeline settings)."""
    from app.sim_record import record_run, run_simulation
    from app.session_cli import session_metadata

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
    sim_camera = None  # through the camera if the session was
    if camera is not None and rec.frames:
        from app.camera_files import load_camera, require_gamma
        from app.paths import SYNTHETIC_CAMERA

        sim_camera = (load_camera(SYNTHETIC_CAMERA), require_gamma(camera))
    frames_hz = float(rec.metadata.get("frames_hz", "0") or 0) if sim_camera else 0.0
    run = run_simulation(scenario, sim_camera, settings, frames_hz=frames_hz or (1.0 if sim_camera else 0.0))
    meta = session_metadata(scenario.name, None, sim_camera)
    meta.update(scenario_toml=text, duration_s=f"{scenario.duration_s:g}", rate_hz=f"{scenario.rate_hz:g}",
                seed=str(scenario.seed), rerun_of=rec.path.name, gains=json.dumps(gains.as_dict()))
    record_run(run, out_path, meta, frames_hz)
    return out_path


def cmd_rerun(args: Any) -> int:
    from app.report import series, summarise

    if not args.out.parent.is_dir():
        raise UserError(f"{args.out}: folder {args.out.parent} does not exist")
    if args.out.resolve() == args.file.resolve():
        raise UserError(f"--out {args.out}: would overwrite the recording being re-run; give another file")
    settings = PipelineSettings()
    if args.pipeline_config is not None:
        if not args.pipeline_config.is_file():
            raise UserError(f"{args.pipeline_config}: no such pipeline config file")
        from core.vision.pipeline import parse_pipeline_settings

        try:
            settings = parse_pipeline_settings(args.pipeline_config.read_text(encoding="utf-8"),
                                               display_path(args.pipeline_config))
        except ConfigError as exc:
            raise UserError(str(exc)) from None
    if args.gains is not None:
        parse_gains(args.gains, Gains())  # the arguments first: no need to read a large file to refuse them
    rec = read_or_fail(args.file)
    camera = recorded_calibration(rec, args.calibration) if rec.frames else None
    note = {"rerun_of": rec.path.name, "pipeline_settings": json.dumps(settings.__dict__)}

    def progress(done: int, total: int) -> None:
        if done == total or done % max(1, total // 10) == 0:
            print(f"  [{done}/{total}] frames", flush=True)

    if args.gains is not None:
        gains = parse_gains(args.gains, params_from_recording(rec).gains)
        print(f"re-simulating {rec.metadata.get('scenario', rec.path.stem)} with "
              + ", ".join(f"{k}={v:g}" for k, v in gains.as_dict().items()), flush=True)
        resimulate(rec, gains, settings, args.out, camera)
        new = read_recording(args.out)
        old_sum, new_sum = summarise(rec, series(rec)), summarise(new, series(new))
        print("per follower: settling time (s) and steady error RMS (cm), recorded -> new")
        def settled(x: object) -> str:
            return "not settled" if x is None else f"{x}"

        for a, b in zip(old_sum["followers"], new_sum["followers"]):  # type: ignore[call-overload]
            print(f"  F{a['follower']}: settling {settled(a['settling_time_s'])} -> {settled(b['settling_time_s'])},"
                  f" steady RMS {a['steady_error_rms_cm']} -> {b['steady_error_rms_cm']},"
                  f" max {a['steady_error_max_cm']} -> {b['steady_error_max_cm']}")
    else:
        if camera is None:
            raise UserError(f"{rec.path.name}: has no camera frames to re-run (recorded with --frames-hz 0, or"
                            " without the camera); --gains re-simulates a simulated session")
        print(f"re-running {len(rec.frames)} recorded frames through the vision pipeline ({camera.source})",
              flush=True)
        r = rerun_frames(rec, camera, settings, progress)
        write_frame_rerun(rec, r, args.out, note)
        print("per follower: new estimates against the recorded ones (RMS), and against the truth where recorded")
        for row in frame_summary(r):
            line = (f"  F{row['follower']}: position {row['position_change_rms_cm']:.2f} cm, heading"
                    f" {row['heading_change_rms_deg']:.2f} deg; tracked {row['tracked_new_pct']:.0f} %"
                    f" (recorded {row['tracked_recorded_pct']:.0f} %)")
            if "new_error_rms_cm" in row:
                line += (f"; error vs truth {row['recorded_error_rms_cm']:.2f} -> {row['new_error_rms_cm']:.2f} cm,"
                         f" {row['recorded_heading_error_rms_deg']:.2f} -> {row['new_heading_error_rms_deg']:.2f} deg")
            print(line)
    print(f"wrote {display_path(args.out)}")
    return 0


def read_or_fail(path: Path) -> Recording:
    from app.session_cli import _load

    return _load(path)
