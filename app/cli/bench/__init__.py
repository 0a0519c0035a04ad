"""`omniformation bench` and `omniformation soak`: speed figures, as ratios and medians within one run.

These machines are shared and noisy, so nothing here is asserted by tests; each figure is the
median of several repeats. It lives in the app package (not a loose script) so the installed
console script can run it anywhere. One module per family, each declaring ``FAMILY``
(app.cli.bench.family says what a family is): plain `bench` runs the default families (the ones
that answer "did this change make it slower?" within minutes), ``--full`` every family,
``--family NAME`` the ones named. The console shows one line per figure; the families' detail
and whatever the services they start print go to a log file the run names; the run is saved as
JSON (figures, commit, machine) and ``--compare A.json B.json`` prints each figure's ratio.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

from app.cli.args import Parser, float_in, int_in
from app.cli.bench.latency import bench_latency
from app.cli.bench.recordings import bench_long_recording, damage_table, loss_cases, replay_probe, write_long_recording
from app.cli.bench.soak import GcPauses, run_soak

if TYPE_CHECKING:
    from app.cli.bench.family import Family

__all__ = ["GcPauses", "bench_latency", "bench_long_recording", "damage_table", "loss_cases", "register",
           "replay_probe", "run_bench", "run_soak", "write_long_recording"]

def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    bench = sub.add_parser("bench", help="measure controller, vision, simulator and live-loop speed")
    bench.add_argument("--long-recording", type=float_in(1.0, 24 * 60, "min"), metavar="MINUTES",
                       help="instead: write a live-like recording this long (vision in the loop, 3 followers, frames at"
                            " 10 Hz) and measure report (peak memory, time) and replay (open, first frame, seeks) on it")
    bench.add_argument("--latency", type=float_in(2.0, 3600.0, "s"), metavar="SECONDS",
                       help="instead: frame-to-command latency for this long on a real rig's path: a 30 fps folder of"
                            " the synthetic rig's pictures, the serial link to emulated robots on a pty, recording on,"
                            " a browser attached; at normal priority, then as run --realtime")
    which = bench.add_mutually_exclusive_group()
    which.add_argument("--full", action="store_true",
                       help="every family, not only the default ones (speed, Foxglove, floods, ROS 2: under 5 minutes here):"
                            " also the page's clients by turns, the fleet, browsers, sweeps, studies (well over 15 minutes)")
    which.add_argument("--family", action="append", metavar="NAME",
                       help="only this family (again for more); `bench --list` names them")
    which.add_argument("--list", action="store_true", help="name every family, the default ones marked, and exit")
    which.add_argument("--compare", nargs=2, type=Path, metavar=("A.json", "B.json"),
                       help="instead: each figure of two saved runs and its ratio B / A (judge a change against its"
                            " parent on one machine)")
    bench.add_argument("--out", type=Path, default=Path("bench-results"), metavar="DIR",
                       help="where the run's JSON and its log go (default bench-results/)")
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
    from app.cli.bench.family import choose, compare, families, read_run
    from app.files import UserError

    if args.latency is not None:  # as `run` does by default, then as `run --realtime`
        bench_latency(args.latency, page_process=True)  # the page in its own process, as `run` serves it
        bench_latency(args.latency, realtime=True, page_process=True)
    elif args.long_recording is not None:
        bench_long_recording(args.long_recording)
    elif args.compare is not None:
        try:
            a, b = (read_run(path) for path in args.compare)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        print(f"{'figure':<58} {'A':>12} {'B':>12} {'B / A':>9}")
        for line in compare(a, b):
            print(line)
    elif args.list:
        for family in families():
            print(f"{family.name:<9} {'default' if family.default else '--full':<8} {family.what}")
    else:
        try:
            chosen = choose(families(), args.full, args.family)
        except ValueError as exc:
            raise UserError(str(exc)) from None
        run_bench(chosen, args.out)
    return 0


def run_bench(chosen: list[Family], out: Path, console: TextIO | None = None) -> dict[str, dict[str, float]]:
    """Measure each family of ``chosen`` in order: one line per figure on ``console`` (this process's
    stdout), every other line (the families' detail, the services they start, their child
    processes) into a log file under ``out``; the run saved as JSON beside it. The figures by family."""
    from app.cli.bench.family import figure_line, machine, record

    out.mkdir(parents=True, exist_ok=True)
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    log, saved = out / f"bench-{stamp}.log", out / f"bench-{stamp}.json"
    say = console if console is not None else _console()
    say.write(f"bench: {', '.join(f.name for f in chosen)}; one line per figure; the services' log: {log}\n")
    say.flush()
    before, started, t0 = machine(), time.time(), time.monotonic()
    figures: dict[str, dict[str, float]] = {}
    with open(log, "a", encoding="utf-8") as log_file, _into(log_file):
        for family in chosen:
            print(f"== {family.name}: {family.what}", file=log_file, flush=True)
            try:
                got = family.run(lambda line: print(line, file=log_file, flush=True))
            except Exception as exc:  # one family that fails is said (its traceback in the log), the others still run
                logging.getLogger(__name__).exception("bench family %s failed", family.name)
                say.write(f"{family.name:<9} failed: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                          f" (the log says more)\n")
                got = {}
            figures[family.name] = got
            for name, value in got.items():
                say.write(figure_line(family.name, name, value) + "\n")
            say.flush()
    saved.write_text(json.dumps(record(figures, started, time.monotonic() - t0, before, log), indent=1) + "\n",
                     encoding="utf-8")
    say.write(f"bench: saved {saved} (bench --compare A.json B.json: each figure's ratio)\n")
    say.flush()
    if console is None and say is not sys.stdout:
        say.close()
    return figures


def _console() -> TextIO:
    """Where the figures go: this process's stdout as it is before the run (a copy of its file
    descriptor, which :func:`_into` moves to the log)."""
    try:
        return os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1, encoding="utf-8", closefd=True)
    except (OSError, ValueError, AttributeError):  # not a file (a test's StringIO): itself
        return sys.stdout


@contextlib.contextmanager
def _into(log_file: TextIO) -> Iterator[None]:
    """This process's stdout and stderr (Python's and file descriptors 1 and 2, so the services'
    threads, logging and child processes too) into ``log_file`` while the families run; back as
    they were after."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    handler = logging.StreamHandler(log_file)  # what the services log (as on stderr: warnings and worse)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    try:
        os.dup2(log_file.fileno(), 1)
        os.dup2(log_file.fileno(), 2)
        with contextlib.redirect_stdout(log_file), contextlib.redirect_stderr(log_file):
            yield
    finally:
        logging.getLogger().removeHandler(handler)
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])
