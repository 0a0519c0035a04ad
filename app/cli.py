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

from app.camera_files import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA
from app.params import MAX_FOLLOWERS
from app.service_config import DEFAULT_CONFIG
from app.paths import UserError, display_path, scenario_names

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
    from core.sim.run import simulate

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
    for out in (args.out, args.plot):
        if out is not None and not out.parent.exists():
            raise UserError(f"{out}: folder {out.parent} does not exist")
    import numpy as np

    tracked = None
    if args.vision:
        from app.camera_files import load_camera
        from core.sim.vision_run import simulate_vision

        rig = load_camera(args.camera)
        calibration = load_camera(args.calibration)
        if rig.model is None:
            raise UserError(f"{display_path(args.camera)}: has no [model]: a synthetic rig is needed to render frames")
        if calibration.gamma is None:
            raise UserError(f"{display_path(args.calibration)}: has no [gamma]; make one with omniformation calibrate")
        vision = simulate_vision(scenario, rig, calibration.gamma)
        log, tracked = vision.log, vision.tracked
        after = log.t >= 0
        lost = (~tracked[after]).sum(axis=0) / scenario.rate_hz
        est = np.linalg.norm(log.p_meas - log.p, axis=-1)[after]
        from core.geometry import wrap_angle

        diff = log.a_meas - log.a
        known = np.isfinite(diff)
        head = np.where(known, np.degrees(np.abs(wrap_angle(np.where(known, diff, 0.0)))), np.nan)[after]
        print(f"vision: start-up manoeuvres took {vision.startup_s:.1f} s; then, per follower:")
        for i in range(log.n):
            print(f"  f{i + 1}: position estimate RMS {np.sqrt(np.nanmean(est[:, i] ** 2)) * 100:.2f} cm,"
                  f" heading RMS {np.sqrt(np.nanmean(head[:, i] ** 2)):.2f} deg, not tracked {lost[i]:.2f} s")
    else:
        log = simulate(scenario)

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
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    import signal

    from app.scenarios import load_scenario
    from app.service import LOOPBACK, Service
    from app.service_config import load_service_config

    config = load_service_config(args.config, MAX_FOLLOWERS)
    scenario = load_scenario(args.scenario) if args.scenario else None
    feedback = args.feedback or config.feedback
    camera = config.camera() if feedback == "vision" else None
    if args.host not in LOOPBACK:
        print(f"warning: serving on {args.host}: anyone who can reach it can command the robots"
              " (there is no authentication)", file=sys.stderr)
    try:
        service = Service(host=args.host, port=args.port, scenario=scenario,
                          n_followers=args.followers or config.followers, rate_hz=args.rate or config.rate_hz,
                          seed=config.seed if args.seed is None else args.seed, camera=camera,
                          dynamics=config.dynamics, noise=config.measurement)
    except OSError as exc:
        raise UserError(f"cannot serve on {args.host}:{args.port}: {exc.strerror or exc}") from None
    signal.signal(signal.SIGTERM, lambda *_: service.loop.stop())
    service.start()
    source = "the vision pipeline on the synthetic camera" if camera else "the simulator's poses plus noise"
    print(f"omniformation: dashboard at {service.url}  (poses from {source}; Ctrl-C to stop)", flush=True)
    try:
        service.wait()
    except KeyboardInterrupt:
        pass
    finally:
        service.close()
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
    run.set_defaults(func=_cmd_run)

    from app.camera_cli import add_parsers as add_camera_parsers

    add_camera_parsers(sub, _positive_float, _int_in, _seed)

    bench = sub.add_parser("bench", help="measure controller and simulator speed")
    bench.set_defaults(func=_cmd_bench)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except UserError as exc:
        print(f"omniformation: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # output piped into `head` and the like
        return 0


if __name__ == "__main__":
    sys.exit(main())
