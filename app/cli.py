"""The `omniformation` command line: one subcommand per job.

User mistakes (bad arguments, bad files) print one line and exit with code 2;
no traceback is shown for them.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import NoReturn, Sequence

from app.params import MAX_FOLLOWERS
from app.paths import DEFAULT_CONFIG, SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, UserError, display_path, scenario_names

EXIT_USAGE = 2
VISION_RATE_HZ = 30.0  # the synthetic camera's frame rate


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (and exit code 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _positive_float(lo: float, hi: float, unit: str, lo_inclusive: bool = False) -> "argparse._ActionType":  # type: ignore[name-defined]
    """An argparse type: a finite number in (lo, hi] (or [lo, hi]), refused in one line otherwise."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        inside = (lo <= value if lo_inclusive else lo < value) and value <= hi
        if not math.isfinite(value) or not inside:
            raise argparse.ArgumentTypeError(f"{text} is outside {'[' if lo_inclusive else '('}{lo:g}, {hi:g}] {unit}")
        return value

    return parse


def _int_in(lo: int, hi: int, what: str = "") -> "argparse._ActionType":  # type: ignore[name-defined]
    """An argparse type: a whole number in [lo, hi], refused in one line otherwise."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"{text} is outside {lo}..{hi}{what}")
        return value

    return parse


_seed = _int_in(0, 2**32 - 1)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from app.scenarios import load_scenario

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
    scenario = scenario.replace(**changes)
    for out in (args.out, args.plot, args.record):
        if out is not None and not out.parent.exists():
            raise UserError(f"{out}: folder {out.parent} does not exist")
    import numpy as np

    from app.sim_record import record_run, run_simulation

    camera = None
    if args.vision:
        from app.camera_files import load_synthetic_rig

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
    if args.out is not None:
        from app.simlog_io import write_csv

        write_csv(log, args.out, tracked)
        print(f"wrote {display_path(args.out)}")
    if args.plot is not None:
        from app.figures import plot_simulation

        plot_simulation(log, args.plot)
        print(f"wrote {display_path(args.plot)}")
    if args.record is not None:
        from app.session_cli import session_metadata

        meta = session_metadata(scenario_name=scenario.name, scenario_path=args.scenario, camera=camera)
        meta.update(duration_s=f"{scenario.duration_s:g}", rate_hz=f"{scenario.rate_hz:g}", seed=str(scenario.seed))
        count = record_run(run, args.record, meta, args.frames_hz)
        print(f"wrote {display_path(args.record)}: {count} ticks, {len(run.frames)} frames,"
              f" {args.record.stat().st_size / 1e6:.1f} MB")
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    import signal

    from app.scenarios import load_scenario
    from app.service import LOOPBACK, Service
    from app.service_config import load_service_config

    config = load_service_config(args.config, MAX_FOLLOWERS)
    scenario = load_scenario(args.scenario) if args.scenario else None
    if args.record is not None and not args.record.parent.is_dir():
        raise UserError(f"{args.record}: folder {args.record.parent} does not exist")
    if args.camera is None and config.frames != "synthetic":
        args.camera = config.frames  # the config names a real camera; the command line wins
    real = args.camera is not None  # a real rig: real camera, real robots, no simulator
    configured_link = config.link if config.link != "sim" or not real else None
    link_spec = args.link or configured_link or ("none" if real else "sim")
    if real and (scenario is not None or args.feedback == "truth" or link_spec == "sim"):
        raise UserError("--camera runs a real rig: it cannot be combined with --scenario, --feedback truth"
                        " or --link sim (give --link serial:PATH, or none to only observe)")
    if not real and (link_spec == "none" or args.leader is not None):
        raise UserError("--link none and --leader need --camera: the simulated team has its own leader and link")
    if args.calibration is not None and not real:
        raise UserError("--calibration goes with --camera (the synthetic camera's is set in the config)")
    from app.backends.serial_link import SerialLink, make_link, parse_link_spec

    try:
        link_port = "" if link_spec == "none" else parse_link_spec(link_spec)
        leader_port = parse_link_spec(args.leader) if args.leader is not None else ""
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if leader_port == "" and args.leader is not None:
        raise UserError(f"--leader {args.leader!r}: must be 'serial:PATH' (the leader base's port)")
    feedback = "vision" if real else args.feedback or config.feedback
    if real:
        from app.camera_files import load_calibration

        camera = load_calibration(args.calibration or config.calibration_path)
    else:
        camera = config.camera() if feedback == "vision" else None
    if args.host not in LOOPBACK:
        print(f"warning: serving on {args.host}: anyone who can reach it can command the robots"
              " (there is no authentication)", file=sys.stderr)
    n_followers = scenario.n if scenario is not None else args.followers or config.followers
    from core.types import Gains

    limits = scenario.gains if scenario is not None else Gains()
    frames = hardware = None
    if real:
        from app.backends.camera_cv import open_frame_source

        try:
            frames = open_frame_source(args.camera, args.camera_fps)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    link = None
    if link_port:
        try:
            link = make_link(link_port, n_followers, baud=args.baud, v_max=limits.v_max, w_max=limits.w_max)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    if real:
        from app.backends.hardware import HardwareTeam

        leader = SerialLink(leader_port, 1, baud=args.baud, addresses=[0]) if leader_port else None
        hardware = HardwareTeam(n_followers, link, leader)
    try:
        service = Service(host=args.host, port=args.port, scenario=scenario,
                          n_followers=n_followers, rate_hz=args.rate or config.rate_hz,
                          seed=config.seed if args.seed is None else args.seed, camera=camera,
                          dynamics=config.dynamics, noise=config.measurement,
                          link=None if real else link, frames=frames, hardware=hardware)
    except OSError as exc:
        for closable in (hardware or link, frames):
            if closable is not None:
                closable.close()
        raise UserError(f"cannot serve on {args.host}:{args.port}: {exc.strerror or exc}") from None
    recorder = None
    if not args.no_record:
        from app.session_cli import start_recording

        recorder = start_recording(service, config, scenario, args.scenario, camera, args.frames_hz, args.record)
        print(f"omniformation: recording to {display_path(recorder.path)}", flush=True)
    # Ctrl-C and SIGTERM only ask the loop to stop: a KeyboardInterrupt could land anywhere
    # (even before the first tick ends), and the loop's own exit is what zeroes the robots.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: service.loop.stop())
    service.start()
    if real:
        source = f"the vision pipeline on camera {args.camera}"
    else:
        source = "the vision pipeline on the synthetic camera" if camera else "the simulator's poses plus noise"
    via = f"; followers on serial {link.port_name}" if link is not None else "; observe only (no link)" if real else ""
    print(f"omniformation: dashboard at {service.url}  (poses from {source}{via}; Ctrl-C to stop)", flush=True)
    try:
        service.wait()
    except KeyboardInterrupt:
        pass
    finally:
        service.close()
        if recorder is not None:
            recorder.close()
            print(f"omniformation: recording finished: {display_path(recorder.path)} ({recorder.ticks} ticks)", flush=True)
    print("omniformation: stopped; all followers commanded to zero", flush=True)
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from app.bench import run_bench

    run_bench()
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="omniformation",
        description="Leader-follower formation control from one omnidirectional camera.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    sub.required = True

    sim = sub.add_parser(
        "simulate",
        help="run a scenario offline and write its CSV and plot",
        description="Run a scenario (a .toml path or a name: " + ", ".join(scenario_names()) + ").",
    )
    sim.add_argument("scenario", help="scenario name from static_config/scenarios or a .toml path")
    sim.add_argument("--out", type=Path, help="write every tick as CSV (SI units, leader frame)")
    sim.add_argument("--plot", type=Path, help="write the paper-style figure (PNG)")
    sim.add_argument("--duration", type=_positive_float(0.0, 86400.0, "s"), help="override the duration (s)")
    sim.add_argument("--rate", type=_positive_float(0.0, 1000.0, "Hz"), help="override the control rate (Hz)")
    sim.add_argument("--seed", type=_seed, help="override the random seed")
    sim.add_argument("--vision", action="store_true",
                     help="feed the controller from the vision pipeline on synthetic frames (default rate 30 Hz)")
    sim.add_argument("--camera", type=Path, default=SYNTHETIC_CAMERA, help="synthetic rig for --vision")
    sim.add_argument("--calibration", type=Path, default=SYNTHETIC_CALIBRATED, help="Γ for --vision (from calibrate)")
    sim.add_argument("--record", type=Path, metavar="FILE.mcap", help="also write the run as a recording (replay, report)")
    sim.add_argument("--frames-hz", type=_positive_float(0.0, 1000.0, "Hz", lo_inclusive=True), default=10.0,
                     help="camera frames per second in the recording (--vision; default 10, 0 = none)")
    sim.add_argument("--jpeg-quality", type=_int_in(1, 100), default=80, help="JPEG quality of recorded frames (default 80)")
    sim.set_defaults(func=_cmd_simulate)

    run = sub.add_parser(
        "run",
        help="serve the live dashboard on the simulated team",
        description="Run the loop and serve the viser dashboard (default: 3 simulated followers).",
    )
    run.add_argument("--scenario", help="start from a scenario's team, formation and gains")
    run.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; others warn)")
    run.add_argument("--port", type=_int_in(0, 65535, " (0 = any free port)"), default=8080, help="port (default 8080, 0 = any free port)")
    run.add_argument("--config", type=Path, default=DEFAULT_CONFIG,
                     help="service config (default static_config/default.toml)")
    run.add_argument("--feedback", choices=("vision", "truth"),
                     help="poses from the vision pipeline (default) or the simulator's truth plus noise")
    run.add_argument("--followers", type=_int_in(1, MAX_FOLLOWERS), help="simulated followers without --scenario (default: config)")
    run.add_argument("--rate", type=_positive_float(0.0, 200.0, "Hz"), help="loop rate (Hz, default: config)")
    run.add_argument("--seed", type=_seed, help="random seed of the simulated team")
    run.add_argument("--link", metavar="sim|serial:PATH|none",
                     help="where commands go: the built-in simulated team (default) or followers on a serial port,"
                          " e.g. serial:/dev/ttyUSB0 or the path `omniformation emulate-follower` prints"
                          " (serial:PORT1,PORT2,... for one port per follower);"
                          " with --camera: serial:PATH, or none (the default) to only observe")
    run.add_argument("--camera", metavar="0|/dev/videoN|VIDEO|FOLDER",
                     help="a real rig: frames from a camera (index or device), a video file or a folder of images")
    run.add_argument("--calibration", type=Path, metavar="CAMERA.toml",
                     help="with --camera: the rig's calibration from `omniformation calibrate` (default: config's)")
    run.add_argument("--camera-fps", type=_positive_float(0.0, 240.0, "Hz"),
                     help="with --camera: play a video file or folder at this rate (default: the file's, or 30)")
    run.add_argument("--leader", metavar="serial:PATH",
                     help="with --camera: the leader base's port (its wheel odometry, for eq. 38); without it the"
                          " leader is taken to stand still")
    run.add_argument("--baud", type=_int_in(1200, 4_000_000), default=115200, help="serial baud rate (default 115200)")
    run.add_argument("--no-record", action="store_true", help="do not record the session (default: recordings/<UTC>_<name>.mcap)")
    run.add_argument("--record", type=Path, metavar="FILE.mcap", help="record to this file instead of recordings/")
    run.add_argument("--frames-hz", type=_positive_float(0.0, 100.0, "Hz", lo_inclusive=True), default=10.0,
                     help="camera frames per second in the recording (default 10, 0 = none)")
    run.set_defaults(func=_cmd_run)

    from app.camera_cli import add_parsers as add_camera_parsers
    from app.session_cli import add_parsers as add_session_parsers

    add_camera_parsers(sub, _positive_float, _int_in, _seed)
    from app.emulator import add_parser as add_emulator_parser

    add_emulator_parser(sub, _int_in, _positive_float(0.0, 1.0, "(a probability)", lo_inclusive=True))
    add_session_parsers(sub, _int_in)

    bench = sub.add_parser("bench", help="measure controller and simulator speed")
    bench.set_defaults(func=_cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    func = args.func
    if isinstance(func, str):  # "module:function": imported only for the command that runs
        import importlib

        module, _, name = func.partition(":")
        func = getattr(importlib.import_module(module), name)
    try:
        return int(func(args))
    except UserError as exc:
        print(f"omniformation: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        return 0


if __name__ == "__main__":
    sys.exit(main())
