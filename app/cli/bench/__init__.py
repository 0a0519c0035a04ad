"""`omniformation bench` and `omniformation soak`: speed figures, as ratios and medians within one run.

These machines are shared and noisy, so nothing here is asserted by tests; each figure is the
median of several repeats. It lives in the app package (not a loose script) so the installed
console script can run it anywhere. One module per family; `bench` runs :data:`FAMILIES` in
order (a new family is one line there: a function taking ``print_fn`` and returning its figures).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from app.cli.args import Parser, float_in, int_in
from app.cli.bench import browsers, fleet, floods, foxglove, loop, ros2, speed, study, sweeps
from app.cli.bench.latency import bench_latency
from app.cli.bench.recordings import bench_long_recording, damage_table, loss_cases, replay_probe, write_long_recording
from app.cli.bench.soak import GcPauses, run_soak

__all__ = ["FAMILIES", "GcPauses", "bench_latency", "bench_long_recording", "damage_table", "loss_cases", "register",
           "replay_probe", "run_bench", "run_soak", "write_long_recording"]

# What `omniformation bench` measures, in this order: each takes print_fn and returns its figures by name.
FAMILIES: list[Callable[[Callable[[str], None]], dict[str, float]]] = [
    speed.run_family,
    sweeps.run_family,
    study.run_family,
    browsers.run_family,
    foxglove.run_family,
    floods.run_family,
    loop.run_family,
    fleet.run_family,
    ros2.run_family,
]


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    bench = sub.add_parser("bench", help="measure controller, vision, simulator and live-loop speed")
    bench.add_argument("--long-recording", type=float_in(1.0, 24 * 60, "min"), metavar="MINUTES",
                       help="instead: write a live-like recording this long (vision in the loop, 3 followers, frames at"
                            " 10 Hz) and measure report (peak memory, time) and replay (open, first frame, seeks) on it")
    bench.add_argument("--latency", type=float_in(2.0, 3600.0, "s"), metavar="SECONDS",
                       help="instead: frame-to-command latency for this long on a real rig's path: a 30 fps folder of"
                            " the synthetic rig's pictures, the serial link to emulated robots on a pty, recording on,"
                            " a browser attached; at normal priority, then as run --realtime")
    bench.set_defaults(func=cmd_bench)
    soak = sub.add_parser("soak", help="run the live service for a long time and measure memory growth and loop rate",
                          description="What `make run` serves (vision in the loop, recording on), one browser"
                                      " connected, for --minutes: the process's RSS and the loop's rate every"
                                      " 10 s, and the RSS growth per hour after the first two minutes.")
    soak.add_argument("--minutes", type=float_in(0.5, 24 * 60, "min"), default=60.0, help="how long (default 60)")
    soak.add_argument("--browsers", type=int_in(0, 3), default=1, help="browsers connected (default 1)")
    soak.add_argument("--scenario", help="run this scenario (e.g. obstacle_course: the scan, the filter and the goal mode"
                                         " all on) instead of the built-in team")
    soak.set_defaults(func=cmd_soak)


def cmd_soak(args: argparse.Namespace) -> int:
    run_soak(args.minutes, args.browsers, scenario=args.scenario)
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    if args.latency is not None:  # as `run` does by default, then as `run --realtime`
        bench_latency(args.latency, page_process=True)  # the page in its own process, as `run` serves it
        bench_latency(args.latency, realtime=True, page_process=True)
    elif args.long_recording is not None:
        bench_long_recording(args.long_recording)
    else:
        run_bench()
    return 0


def run_bench(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """Every family of :data:`FAMILIES`, in order; their figures by name."""
    results: dict[str, float] = {}
    for family in FAMILIES:
        results.update(family(print_fn))
    return results
