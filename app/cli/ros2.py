"""ROS 2 on the command line: ``run --ros2`` (the service as a ROS 2 node, ``--leader ros2:/cmd_vel``,
``--ros2-control``) and ``emulate-base --ros2`` (a ROS 2 base for tests and demos). docs/ros2.md."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from app.cli.args import Parser, float_in, int_in
from app.files import UserError

if TYPE_CHECKING:
    from app.backends.links import LinkSpec

    from app.fleet.security import FleetKeys
    from app.services.ros2_node import Ros2Plan

DOMAIN_HELP = "the ROS 2 domain (ROS_DOMAIN_ID, 0..232; default 0)"


def add_run_args(run: argparse.ArgumentParser) -> None:
    """``run``'s ROS 2 options (its --zenoh-connect and --keys are the fleet's, shared)."""
    from core.rmw_zenoh import DOMAIN_MAX

    run.add_argument("--ros2", action="store_true",
                     help="be a ROS 2 node on rmw_zenoh: /tf, the followers, slots, formation error, camera and"
                          " status out, through the ROS 2 router at --zenoh-connect (docs/ros2.md)")
    run.add_argument("--ros2-domain", type=int_in(0, DOMAIN_MAX), default=0, metavar="N", help=DOMAIN_HELP)
    run.add_argument("--ros2-control", action="store_true",
                     help="--ros2: take /omniformation/stop (std_msgs/msg/Bool) and /omniformation/goal"
                          " (geometry_msgs/msg/PoseStamped) from ROS, with the page's checks")
    run.add_argument("--ros2-intruder-stop", action="store_true",
                     help="--leader ros2:TOPIC: STOP when another publisher appears on the base's command topic"
                          " (without it: an alarm on the page, an event, a line on stderr; docs/ros2.md)")


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    from core.rmw_zenoh import DOMAIN_MAX

    base = sub.add_parser(
        "emulate-base",
        help="an emulated ROS 2 mobile base: /cmd_vel in, /odom out (for tests and demos)",
        description="A ROS 2 base on rmw_zenoh's wire format: takes geometry_msgs/msg/Twist on /cmd_vel, publishes"
                    " nav_msgs/msg/Odometry on /odom, moved by the simulator's robot dynamics (docs/ros2.md).",
    )
    base.add_argument("--ros2", action="store_true", required=True, help="on ROS 2 (rmw_zenoh); the only kind so far")
    base.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT",
                      help="the ROS 2 Zenoh router (default tcp/127.0.0.1:7447); loopback only without --keys,"
                           " tls/HOST:PORT with them")
    base.add_argument("--keys", type=Path, metavar="DIR",
                      help="one identity's bundle of the fleet's keys (`fleet-keys DIR --ros2` writes DIR/ros2/):"
                           " mutual TLS to the router (docs/ros2.md)")
    base.add_argument("--ros2-domain", type=int_in(0, DOMAIN_MAX), default=0, metavar="N", help=DOMAIN_HELP)
    base.add_argument("--rate", type=float_in(0.0, 1000.0, "Hz"), default=50.0, help="odometry rate (Hz, default 50)")
    base.add_argument("--speed-scale", type=float_in(0.0, 2.0, "", lo_inclusive=True), default=1.0, metavar="S",
                      help="the base really moves S times what it is told (a slipping or mis-calibrated base; 0..2,"
                           " default 1); its odometry reports what it really did")
    base.add_argument("--seconds", type=float_in(0.0, 7 * 24 * 3600.0, "s"), help="stop after this long (default: Ctrl-C)")
    base.set_defaults(func=cmd_emulate_base)


def cmd_emulate_base(args: argparse.Namespace) -> int:
    import signal
    import threading

    from app.services.ros2_node import run_emulated_base

    keys = load_keys(args.keys)
    if keys is not None and not args.zenoh_connect:
        raise UserError("--keys needs --zenoh-connect tls/HOST:PORT: the ROS 2 machines' router")
    done = threading.Event()
    with run_emulated_base(args.zenoh_connect or ["tcp/127.0.0.1:7447"], keys, args.ros2_domain, args.rate,
                           args.speed_scale) as base:
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: done.set())
        print(f"omniformation: ROS 2 base on domain {args.ros2_domain}: /cmd_vel in, /odom out at {args.rate:g} Hz"
              " (Ctrl-C to stop)", flush=True)
        done.wait(args.seconds)
    print(f"omniformation: base stopped after {len(base.commands)} commands"
          f" ({base.node.dropped} malformed dropped)", flush=True)
    return 0


def load_keys(directory: Path | None) -> FleetKeys | None:
    """``--keys DIR`` for a ROS 2 session: one identity's bundle, checked (UserError, one line)."""
    if directory is None:
        return None
    from app.ros2.session import ros2_keys

    try:
        return ros2_keys(directory)
    except ValueError as exc:
        raise UserError(str(exc)) from None


# -- run --ros2 ------------------------------------------------------------------------------
def check_run_args(args: argparse.Namespace, leader: LinkSpec | None) -> None:
    """Before anything opens: a ROS 2 leader base (``--leader ros2:TOPIC[:stamped]``, looked up in the
    link registry by the caller) needs --ros2; --ros2 needs --zenoh-connect."""
    if leader is not None and leader.scheme == "ros2" and not args.ros2:
        raise UserError(f"--leader {args.leader}: a ROS 2 base needs --ros2 and --zenoh-connect ROUTER")
    if not args.ros2 and (args.ros2_control or args.ros2_domain):
        raise UserError("--ros2-control and --ros2-domain go with --ros2")
    if args.ros2_intruder_stop and (leader is None or leader.scheme != "ros2"):
        raise UserError("--ros2-intruder-stop goes with --leader ros2:TOPIC (a ROS 2 base's command topic)")
    if args.ros2 and (args.fleet is not None or args.arena is not None):
        raise UserError("--ros2 cannot be combined with --fleet or --arena: its --zenoh-connect is the ROS 2 machines'"
                        " router (the fleet's bus is a separate Zenoh network)")
    if args.ros2 and not args.zenoh_connect:
        raise UserError("--ros2 needs --zenoh-connect ENDPOINT: the ROS 2 machines' Zenoh router"
                        " (e.g. tcp/127.0.0.1:7447, where `ros2 run rmw_zenoh_cpp rmw_zenohd` listens)")
    args.ros2_keys = load_keys(args.keys) if args.ros2 else None


def ros2_plan(args: argparse.Namespace, leader: LinkSpec | None = None) -> Ros2Plan | None:
    """``run --ros2`` as the services take it (checked by check_run_args; None without --ros2);
    ``leader``: the --leader spec, a ROS 2 base's when its scheme is ros2."""
    if not args.ros2:
        return None
    from app.services.ros2_node import Ros2Plan

    base = leader if leader is not None and leader.scheme == "ros2" else None
    return Ros2Plan(tuple(args.zenoh_connect), args.ros2_keys, args.ros2_domain, base, args.ros2_control,
                    args.ros2_intruder_stop)
