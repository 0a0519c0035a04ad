"""`omniformation simulate`: a scenario offline, as CSV, figure and recording."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from app.cli.args import Parser, float_in, int_in, seed
from core.sim.profiles import GoalProfile

if TYPE_CHECKING:
    import numpy as np

    from core.config import Scenario
    from core.sim.stepped import SafetyLog
from app.files import (SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, UserError, check_new_file, display_path,
                       scenario_names)

PLOT_SUFFIXES = (".png", ".pdf", ".svg", ".jpg")

VISION_RATE_HZ = 30.0  # the synthetic camera's frame rate


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    sim = sub.add_parser(
        "simulate",
        help="run a scenario offline and write its CSV and plot",
        description="Run a scenario (a .toml path or a name: " + ", ".join(scenario_names()) + ").",
    )
    sim.add_argument("scenario", help="scenario name from static_config/scenarios or a .toml path")
    sim.add_argument("--out", type=Path, help="write every tick as CSV (SI units, leader frame)")
    sim.add_argument("--plot", type=Path, help="write the paper-style figure (PNG)")
    sim.add_argument("--duration", type=float_in(0.0, 86400.0, "s"), help="override the duration (s)")
    sim.add_argument("--rate", type=float_in(0.0, 1000.0, "Hz"), help="override the control rate (Hz)")
    sim.add_argument("--seed", type=seed, help="override the random seed")
    sim.add_argument("--vision", action="store_true",
                     help="feed the controller from the vision pipeline on synthetic frames (default rate 30 Hz)")
    sim.add_argument("--camera", type=Path, default=SYNTHETIC_CAMERA, help="synthetic rig for --vision")
    sim.add_argument("--calibration", type=Path, default=SYNTHETIC_CALIBRATED, help="Γ for --vision (from calibrate)")
    sim.add_argument("--record", type=Path, metavar="FILE.mcap", help="also write the run as a recording (replay, report)")
    sim.add_argument("--frames-hz", type=float_in(0.0, 1000.0, "Hz", lo_inclusive=True), default=10.0,
                     help="camera frames per second in the recording (--vision; default 10, 0 = none)")
    sim.add_argument("--jpeg-quality", type=int_in(1, 100), default=80, help="JPEG quality of recorded frames (default 80)")
    sim.add_argument("--no-safety", action="store_true",
                     help="run a scenario that has a [safety] table without the safety filter (to compare)")
    sim.set_defaults(func=cmd_simulate)



def cmd_simulate(args: argparse.Namespace) -> int:
    from app.files import load_scenario

    scenario = load_scenario(args.scenario)
    changes: dict[str, object] = {}
    if args.duration is not None:
        changes["duration_s"] = args.duration
    if args.rate is not None:
        changes["rate_hz"] = args.rate
    elif args.vision:
        changes["rate_hz"] = VISION_RATE_HZ  # one control step per camera frame
    if args.seed is not None:
        changes["seed"] = args.seed
    if args.no_safety:
        changes["safety"] = None
    scenario = scenario.replace(**changes)
    if args.out is not None:
        check_new_file(args.out, "CSV log", ".csv")
    if args.plot is not None:
        check_new_file(args.plot, "figure", *PLOT_SUFFIXES)
    if args.record is not None:
        check_new_file(args.record, "recording", ".mcap")
        if args.record.exists():
            raise UserError(f"{args.record}: exists; a recording is never written over another (give a new name)")
    import numpy as np

    from app.recording.simulated import record_run, run_simulation

    camera = None
    if args.vision:
        from app.files import load_synthetic_rig

        camera = load_synthetic_rig(args.camera, args.calibration)
    run = run_simulation(scenario, camera, frames_hz=args.frames_hz if args.record is not None else 0.0,
                         jpeg_quality=args.jpeg_quality)
    log, vision = run.log, run.vision
    tracked = vision.tracked if vision is not None else None
    if vision is not None:
        after = log.t >= 0
        lost = (~vision.tracked[after]).sum(axis=0) / scenario.rate_hz
        est = np.linalg.norm(log.p_meas - log.p, axis=-1)[after]
        from core.geometry import wrap_angle

        diff = log.a_meas - log.a
        known = np.isfinite(diff)
        head = np.where(known, np.degrees(np.abs(wrap_angle(np.where(known, diff, 0.0)))), np.nan)[after]
        print(f"vision: start-up manoeuvres took {vision.startup_s:.1f} s; then, per follower:")
        for i in range(log.n):
            print(f"  f{i + 1}: position estimate RMS {np.sqrt(np.nanmean(est[:, i] ** 2)) * 100:.2f} cm,"
                  f" heading RMS {np.sqrt(np.nanmean(head[:, i] ** 2)):.2f} deg, not tracked {lost[i]:.2f} s")

    err = np.linalg.norm(log.error, axis=-1)
    final = ", ".join(f"f{i + 1} {err[-1, i] * 100:.2f} cm" for i in range(log.n))
    print(f"{scenario.name}: {scenario.duration_s:g} s at {scenario.rate_hz:g} Hz, {log.n} followers; final position error {final}")
    if run.safety is not None:
        print(safety_line(run.safety, log.t, scenario))
    if args.out is not None:
        from app.recording.csv_log import write_csv

        try:
            write_csv(log, args.out, tracked)
        except OSError as exc:
            raise UserError(f"{args.out}: cannot write: {exc.strerror or exc}") from None
        print(f"wrote {display_path(args.out)}")
    if args.plot is not None:
        from app.recording.plots import plot_simulation

        try:
            plot_simulation(log, args.plot)
        except OSError as exc:
            raise UserError(f"{args.plot}: cannot write: {exc.strerror or exc}") from None
        print(f"wrote {display_path(args.plot)}")
    if args.record is not None:
        from app.recording.session import session_metadata

        meta = session_metadata(scenario_name=scenario.name, scenario_path=args.scenario, camera=camera)
        meta.update(duration_s=f"{scenario.duration_s:g}", rate_hz=f"{scenario.rate_hz:g}", seed=str(scenario.seed))
        count = record_run(run, args.record, meta, args.frames_hz)
        print(f"wrote {display_path(args.record)}: {count} ticks, {len(run.frames)} frames,"
              f" {args.record.stat().st_size / 1e6:.1f} MB")
    return 0




def safety_line(sf: "SafetyLog", t: "np.ndarray", scenario: "Scenario") -> str:
    """What a stepped run says about safety, from the simulator's truth."""
    import math

    import numpy as np

    after = t >= 0
    d = sf.min_distance[after]
    under = d < 0.25
    episodes = int(np.count_nonzero(np.diff(np.concatenate([[0], under.astype(np.int8)])) == 1))
    parts = [f"safety filter {'on' if scenario.safety is not None else 'off'}: closest two robots {d.min() * 100:.1f} cm,"
             f" {int(under.sum())} ticks ({episodes} times) under 25 cm"]
    if np.isfinite(sf.obstacle_gap).any():
        parts.append(f"closest follower body to an obstacle {(sf.obstacle_gap[after].min() - 0.15) * 100:.1f} cm,"
                     f" the leader's {(sf.leader_gap[after].min() - 0.25) * 100:.1f} cm")
    acted = sum(1 for s_ in sf.status if s_ == "filtered")
    failed = sum(1 for s_ in sf.status if s_ in ("infeasible", "no solver"))
    parts.append(f"filter acted on {acted} ticks, failed on {failed}")
    if isinstance(scenario.leader, GoalProfile):
        reached = f"reached at {sf.goal_reached_s:.1f} s" if math.isfinite(sf.goal_reached_s) else "NOT reached"
        parts.append(f"goal {reached}; narrowest formation {sf.scale.min():.2f}")
    return "; ".join(parts)
