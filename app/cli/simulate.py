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
    from core.control.tuning import GainRange
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
    sim.add_argument("--rate", type=float_in(1.0, 1000.0, "Hz", lo_inclusive=True), help="override the control rate (Hz)")
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
    sim.add_argument("--latency-ms", type=float_in(0.0, 2000.0, "ms", lo_inclusive=True), metavar="MS",
                     help="a real rig's delay from camera to robot: split between camera and radio as the scenario's"
                          " [latency] does (default 60 %% camera, 40 %% radio), with its jitter")
    sim.add_argument("--no-compensation", action="store_true",
                     help="with latency: the controller does not predict the followers over it (to compare)")
    sim.set_defaults(func=cmd_simulate)

    tune = sub.add_parser(
        "tune",
        help="sweep one or two gains over a step test in the simulator; write the table and the figure",
        description="Run a step test (an offset of one follower's slot, a formation switch, or a step of the"
                    " leader's turn rate) in the simulator for every point of a grid of one or two gains, starting"
                    " from the scenario's team settled on its slots, and score each run (settling time to 2 cm,"
                    " overshoot, steady error RMS, effort).",
    )
    tune.add_argument("scenario", help="scenario name from static_config/scenarios or a .toml path")
    tune.add_argument("--gain", action="append", required=True, metavar="NAME=LO:HI:COUNT",
                      help="a gain and its values (COUNT from LO to HI); once or twice, e.g. --gain k_w2=1:4:7")
    tune.add_argument("--test", choices=("offset", "switch", "turn"), default="offset", help="the step (default offset)")
    tune.add_argument("--follower", type=int_in(1, 8), default=1, help="offset: whose slot moves (default 1)")
    tune.add_argument("--size", type=float, default=None,
                      help="offset: cm sideways (default 10); turn: deg/s added to the leader's turn (default 5)")
    tune.add_argument("--formation", default="line abreast", help="switch: the preset switched to (default line abreast)")
    tune.add_argument("--window", type=float_in(0.0, 600.0, "s"), default=10.0, help="seconds measured (default 10)")
    tune.add_argument("--vision", action="store_true", help="vision in the loop (the synthetic rig) instead of truth")
    tune.add_argument("--camera", type=Path, default=SYNTHETIC_CAMERA, help="synthetic rig for --vision")
    tune.add_argument("--calibration", type=Path, default=SYNTHETIC_CALIBRATED, help="Γ for --vision")
    tune.add_argument("--out", type=Path, required=True, help="folder for sweep.csv, sweep.png, summary.md and study/")
    tune.add_argument("--workers", type=int_in(1, 1024),
                      help="local worker processes the runs share (default: the CPUs less one, at least 1)")
    tune.set_defaults(func=cmd_tune)



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
    duration = float(changes.get("duration_s", scenario.duration_s))  # type: ignore[arg-type]
    rate = float(changes.get("rate_hz", scenario.rate_hz))  # type: ignore[arg-type]
    if duration * rate < 1.0:
        raise UserError(f"--duration {duration:g} s: shorter than one control tick (1/{rate:g} s at {rate:g} Hz)")
    if args.seed is not None:
        changes["seed"] = args.seed
    if args.no_safety:
        changes["safety"] = None
    if args.latency_ms is not None or args.no_compensation:
        from core.config import Latency

        own = scenario.latency
        share = own.camera_s / own.total_s if own.total_s > 0 else 0.6
        total = args.latency_ms / 1e3 if args.latency_ms is not None else own.total_s
        changes["latency"] = Latency.split(total, share, own.jitter_s, compensate=not args.no_compensation)
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
    lat = scenario.latency
    if lat.total_s > 0 or lat.jitter_s > 0 or args.latency_ms is not None:
        settled = log.t >= min(40.0, 0.5 * scenario.duration_s)
        rms = float(np.sqrt(np.mean(err[settled] ** 2))) if settled.any() else float("nan")
        print(f"latency: camera {lat.camera_s * 1e3:.0f} ms + radio {lat.radio_s * 1e3:.0f} ms (jitter up to"
              f" {lat.jitter_s * 1e3:.0f} ms), {'compensated' if lat.compensate else 'not compensated'}; formation RMS"
              f" from t = {min(40.0, 0.5 * scenario.duration_s):g} s: {rms * 100:.2f} cm")
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
        from app.figures import plot_simulation

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


def tune_study_text(args: argparse.Namespace, ranges: "list[GainRange]", seed: int) -> str:
    """`tune`'s sweep as a study file: the step test from the team settled on its slots, a grid of
    one or two gains, one run per point (written to OUT/study/study.toml)."""
    from pathlib import Path as _Path

    scen = args.scenario
    if scen.endswith(".toml"):
        scen = str(_Path(scen).resolve())
    lines = ["# omniformation tune, as a study (docs/studies.md)", "[study]", f"scenario = {_toml_str(scen)}",
             f'feedback = "{"vision" if args.vision else "truth"}"', f"seed = {seed}", "replicates = 1"]
    if args.vision:
        lines += [f"camera = {_toml_str(str(_Path(args.camera).resolve()))}",
                  f"calibration = {_toml_str(str(_Path(args.calibration).resolve()))}"]
    lines += ["",
             "[test]", f'kind = "{args.test}"', f"window_s = {args.window!r}"]
    if args.test == "offset":
        lines += [f"follower = {args.follower}", f"size_cm = {float(args.size if args.size is not None else 10.0)!r}"]
    elif args.test == "turn":
        lines.append(f"size_deg_s = {float(args.size if args.size is not None else 5.0)!r}")
    else:
        lines.append(f"formation = {_toml_str(args.formation)}")
    lines += ["", "[grid]"]
    for r in ranges:
        lo, hi, n = float(r.values[0]), float(r.values[-1]), len(r.values)
        lines.append(f'"gains.{r.name}" = {{lo = {lo!r}, hi = {hi!r}, n = {n}}}')
    return "\n".join(lines) + "\n"


def _toml_str(text: str) -> str:
    import json

    return json.dumps(text)  # a TOML basic string is a JSON string


def cmd_tune(args: argparse.Namespace) -> int:
    import math
    import time

    import numpy as np

    from app.files import load_scenario, prepare_out_dir
    from app.figures import sweep_figure
    from app.study.session import parse_study_text, run_session
    from app.study.store import StudyFolder
    from core.control.tuning import StepScore, StepTest, check_step_test, parse_gain_range, sweep_grid
    from core.sim.sweep import BEST_RULE, LEAD_S, SweepResult, settled_start
    from core.study.spec import point_key

    if len(args.gain) > 2:
        raise UserError(f"--gain given {len(args.gain)} times: a sweep takes one or two gains")
    try:
        ranges = [parse_gain_range(g) for g in args.gain]
    except ValueError as exc:
        raise UserError(f"--gain {exc}") from None
    scenario = load_scenario(args.scenario)
    try:
        grid = sweep_grid(ranges, scenario.gains)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    size = args.size if args.size is not None else (10.0 if args.test == "offset" else 5.0)
    if not math.isfinite(size):
        raise UserError(f"--size {size!r}: must be a finite number")
    scaled = size / 100.0 if args.test == "offset" else math.radians(size)
    test = StepTest(args.test, args.follower - 1, scaled, args.formation, args.window)
    base = settled_start(scenario)
    why = check_step_test(test, base.n)
    if why:
        raise UserError(f"--test {args.test}: {why}")
    text = tune_study_text(args, ranges, scenario.seed)
    spec = parse_study_text(text, "tune's study")
    prepare_out_dir(args.out)
    study_dir = args.out / "study"
    study_dir.mkdir(exist_ok=True)
    (study_dir / "study.toml").write_text(text, encoding="utf-8")
    print(f"tune {scenario.name}: {test.label()} over {' x '.join(r.label() for r in ranges)}"
          f" ({len(grid)} runs, {'vision' if args.vision else 'truth'} feedback)", flush=True)
    start = time.perf_counter()
    session = run_session(spec, study_dir / "study.toml", study_dir, args.workers, None, overwrite=True)
    rows = {r["point"]: r for r in StudyFolder(study_dir).table().to_pylist()}
    scores: list[StepScore | None] = []
    for g in grid:
        row = rows.get(point_key({f"gains.{r.name}": float(getattr(g, r.name)) for r in ranges}))
        if row is None:
            scores.append(None)
            continue
        one = [float(row[k]) if row[k] is not None else math.nan
               for k in ("settling_s", "overshoot_m", "final_rms_m", "effort")]
        settle, over, steady, effort = (np.array([v]) for v in one)
        scores.append(StepScore(settle, over, steady, effort, 0))  # the team's figures, as tune shows them
    result = SweepResult(tuple(ranges), test, spec.feedback, tuple(grid), tuple(scores), time.perf_counter() - start,
                         session.outcome.interrupted)
    if session.outcome.interrupted:
        raise KeyboardInterrupt
    (args.out / "sweep.csv").write_text(result.csv(), encoding="utf-8")
    fig = sweep_figure(result)
    fig.savefig(args.out / "sweep.png", dpi=110)
    best = result.best()
    lines = [f"# Sweep: {scenario.name}, {test.label()}", "",
             f"- {len(grid)} runs with {result.feedback} feedback in {result.seconds:.1f} s"
             f" on {session.outcome.workers} worker{'s' if session.outcome.workers != 1 else ''}",
             f"- from the team settled on its slots; the step at {LEAD_S:g} s, measured for {test.window_s:g} s",
             f"- {BEST_RULE}: {result.point_label(best) if best is not None else 'none'}",
             "- Pareto front (settling time vs. overshoot): " + "; ".join(result.point_label(k) for k in result.pareto()),
             "", "sweep.csv: every point; sweep.png: heat map (or line) and Pareto plot; study/: the sweep as a study"
             " (its runs as Parquet, manifest, summary, plots: docs/studies.md)."]
    (args.out / "summary.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    for name in ("sweep.csv", "sweep.png", "summary.md"):
        print(f"wrote {display_path(args.out / name)}")
    print(lines[4][2:])
    print(f"{len(grid)} runs in {result.seconds:.1f} s")
    if session.outcome.failed:
        print(f"{session.outcome.failed} runs failed: {display_path(study_dir / 'failures.parquet')}")
    return 0
