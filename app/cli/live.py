"""`omniformation run`: the live service on the simulated team or a real rig."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from app.cli.args import Parser, float_in, int_in, port, seed, token_arg
from app.files import DEFAULT_CONFIG, UserError, check_new_file
from app.params import MAX_FOLLOWERS

if TYPE_CHECKING:
    from app.contracts import FollowerLink, Rig
    from app.services.live import Service
    from app.services.run import FleetPlan, RadioPlan, RunPlan
    from core.fleet import FleetScenario


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    run = sub.add_parser(
        "run",
        help="serve the live dashboard on the simulated team",
        description="Run the loop and serve the viser dashboard (default: 3 simulated followers).",
    )
    run.add_argument("--scenario", help="start from a scenario's team, formation and gains")
    run.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; others warn)")
    run.add_argument("--port", type=port, default=8080, help="port (default 8080, 0 = any free port)")
    run.add_argument("--token", type=token_arg, help="the token browsers must present on a non-loopback --host"
                                                      " (default: a new one each run, printed in the URL)")
    run.add_argument("--viewer-token", type=token_arg,
                     help="the token of a second, view-only URL: it shows everything and may press STOP, nothing else"
                          " (default: a new one each run, printed)")
    run.add_argument("--config", type=Path, default=DEFAULT_CONFIG,
                     help="service config (default static_config/default.toml)")
    run.add_argument("--feedback", choices=("vision", "truth"),
                     help="poses from the vision pipeline (default) or the simulator's truth plus noise")
    run.add_argument("--followers", type=int_in(1, MAX_FOLLOWERS), help="simulated followers without --scenario (default: config)")
    run.add_argument("--rate", type=float_in(1.0, 200.0, "Hz", lo_inclusive=True), help="loop rate (Hz, default: config)")
    run.add_argument("--seed", type=seed, help="random seed of the simulated team")
    run.add_argument("--link", metavar="sim|serial:PATH|none",
                     help="where commands go: the built-in simulated team (default) or followers on a serial port,"
                          " e.g. serial:/dev/ttyUSB0 or the path `omniformation emulate-follower` prints"
                          " (serial:PORT1,PORT2,... for one port per follower);"
                          " with --camera: serial:PATH, or none (the default) to only observe")
    run.add_argument("--camera", metavar="0|/dev/videoN|VIDEO|FOLDER",
                     help="a real rig: frames from a camera (index or device), a video file or a folder of images")
    run.add_argument("--calibration", type=Path, metavar="CAMERA.toml",
                     help="with --camera: the rig's calibration from `omniformation calibrate` (default: config's)")
    run.add_argument("--camera-fps", type=float_in(0.0, 240.0, "Hz"),
                     help="with --camera: play a video file or folder at this rate (default: the file's, or 30)")
    run.add_argument("--leader", metavar="serial:PATH|ros2:/TOPIC",
                     help="with --camera: the leader base's port (its wheel odometry, for eq. 38); without it the"
                          " leader is taken to stand still. ros2:/cmd_vel (ros2:/cmd_vel:stamped for TwistStamped),"
                          " with --ros2: a ROS 2 base, its odometry from /odom (also with the simulated team)")
    run.add_argument("--baud", type=int_in(1200, 4_000_000), default=115200, help="serial baud rate (default 115200)")
    run.add_argument("--radio-id", type=int_in(1, 250), metavar="N",
                     help="with --link serial:PATH on a radio other leaders share: this leader's number (1..250);"
                          " it claims its robots and drives only those it owns (docs/follower-protocol.md,"
                          " Ownership)")
    run.add_argument("--radio-key", type=Path, metavar="LEADER.radio",
                     help="with --link serial:PATH: this leader's radio key (`fleet-keys` writes DIR/radio/<id>.radio);"
                          " every frame is authenticated with it and only the fleet's robots' replies count")
    run.add_argument("--radio-counter", type=Path, metavar="FILE",
                     help="with --radio-key: keep the frame counter's high-water mark here too (the counter starts"
                          " at the wall clock in ms otherwise; docs/follower-protocol.md)")
    run.add_argument("--allow-unauthenticated-radio", action="store_true",
                     help="drive robots that speak only protocol 1/2, and use a shared radio without --radio-key;"
                          " the status and the recording say so on every tick")
    run.add_argument("--no-record", action="store_true", help="do not record the session (default: recordings/<UTC>_<name>.mcap)")
    run.add_argument("--recordings", type=Path, metavar="DIR",
                     help="where sessions are recorded and listed for replay (default: recordings/ in the working folder)")
    run.add_argument("--record", type=Path, metavar="FILE.mcap", help="record to this file instead of recordings/")
    run.add_argument("--frames-hz", type=float_in(0.0, 100.0, "Hz", lo_inclusive=True), default=10.0,
                     help="camera frames per second in the recording (default 10, 0 = none)")
    run.add_argument("--arena", metavar="FLEET",
                     help="lead a team in a fleet's shared arena (`omniformation arena FLEET` runs it; with"
                          " --leader-id; the fleet's name is the scenario's unless --fleet gives one)")
    run.add_argument("--fleet", metavar="NAME", help="join this fleet on the Zenoh bus (docs/fleet-protocol.md)")
    run.add_argument("--leader-id", metavar="ID", help="this leader's name in the fleet (with --fleet)")
    from app.cli.fleet import add_bus_args
    from app.cli.foxglove_args import add_foxglove_args

    add_bus_args(run, prefix="--fleet: ")
    run.add_argument("--fleet-control", action="store_true",
                     help="--fleet: take gains, formation and motion changes from the bus (STOP is always taken)")
    from app.cli import ros2

    ros2.add_run_args(run)
    run.add_argument("--realtime", action="store_true",
                     help="the loop's and the camera's threads on real-time scheduling (SCHED_FIFO; needs root,"
                          " CAP_SYS_NICE or an rtprio limit): fewer latency spikes on a busy machine")
    where = run.add_mutually_exclusive_group()
    where.add_argument("--loop-process", action="store_true",
                       help="the default: the loop in a process of its own, the page served from another, its"
                            " client (docs/safety.md, \"The page in a process of its own\")")
    where.add_argument("--one-process", action="store_true",
                       help="the page in the loop's process, as before the loop had one of its own (what `bench`"
                            " compares against); a flood of page clients then shares the loop's interpreter")
    run.add_argument("--reserve-cpu", action="store_true",
                     help="keep a CPU for the loop's thread (the highest one no other loop keeps): the service's"
                          " other threads and its page run on the rest. With a browser on this machine, start it off"
                          " that CPU (taskset); README, \"Speed\"")
    add_foxglove_args(run)
    run.set_defaults(func=cmd_run)


def say(text: str, err: bool = False) -> None:
    """A line for people: what the service did (stdout) or a warning (stderr)."""
    print(text, file=sys.stderr if err else sys.stdout, flush=True)


def cmd_run(args: argparse.Namespace) -> int:
    """The live service: check everything into a plan, then the services build, wire and close it
    (app.services.run); Ctrl-C and SIGTERM ask the loop to stop, which zeroes the robots."""
    import signal

    from app.services.run import compose

    plan = _plan_run(args)
    with compose(plan, say) as running:
        service = running.service
        # Ctrl-C and SIGTERM only ask the loop to stop: a KeyboardInterrupt could land anywhere
        # (even before the first tick ends), and the loop's own exit is what zeroes the robots.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: service.loop.stop())
        service.start()
        _say_where(args, plan, service, running.link)
        try:
            service.wait()
        except KeyboardInterrupt:
            pass
    print("omniformation: stopped; all followers commanded to zero", flush=True)
    if running.twin is not None:  # it missed its twin at start and gave way to it
        raise UserError(running.twin)
    return 0


def _plan_run(args: argparse.Namespace) -> RunPlan:
    """Every check of the command line against the config, before anything is opened."""
    from app.cli.foxglove_args import foxglove_plan
    from app.cli.ros2 import check_run_args, ros2_plan
    from app.services.run import RunPlan
    from app.files import load_scenario
    from app.live.config import load_service_config

    from app.backends.links import FOLLOWERS, LEADER, LINK_TYPES, parse_link

    try:  # the link registry says what --leader takes (app.backends.links)
        leader = parse_link(args.leader, LEADER) if args.leader is not None else None
    except ValueError as exc:
        raise UserError(str(exc)) from None
    check_run_args(args, leader)
    if args.viewer_token is not None and args.viewer_token == args.token:
        raise UserError("--viewer-token: must differ from --token (a viewer may not command the robots)")
    config = load_service_config(args.config, MAX_FOLLOWERS)
    fleet_scenario = _check_fleet_args(args)
    scenario = load_scenario(args.scenario) if args.scenario else None
    if scenario is not None and scenario.n > MAX_FOLLOWERS:
        raise UserError(f"--scenario {args.scenario}: {scenario.n} followers; the live service drives 1..{MAX_FOLLOWERS}"
                        " (simulate runs any number)")
    if args.record is not None:
        check_new_file(args.record, "recording", ".mcap")
        if args.record.exists():
            raise UserError(f"{args.record}: exists; a recording is never written over another (give a new name)")
    if args.camera is None and config.frames != "synthetic":
        args.camera = config.frames  # the config names a real camera; the command line wins
    real = args.camera is not None
    configured_link = config.link if config.link != "sim" or not real else None
    link_spec = args.link or configured_link or ("none" if real else "sim")
    try:  # the link registry says what --link takes (app.backends.links)
        link = parse_link(link_spec, FOLLOWERS)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if real and (scenario is not None or args.feedback == "truth" or link.scheme == "sim"):
        raise UserError("--camera runs a real rig: it cannot be combined with --scenario, --feedback truth"
                        " or --link sim (give --link serial:PATH, or none to only observe)")
    if not real and (link.scheme == "none" or (leader is not None and not LINK_TYPES[leader.scheme].leads_simulated_team)):
        raise UserError("--link none and --leader need --camera: the simulated team has its own leader and link")
    if args.calibration is not None and not real:
        raise UserError("--calibration goes with --camera (the synthetic camera's is set in the config)")
    from app.backends.serial_link import same_device

    followers_ports = link.ports
    link_port = ",".join(followers_ports)
    leader_ports = leader.ports if leader is not None else ()
    if len(leader_ports) > 1:
        raise UserError(f"--leader {args.leader!r}: one port, the leader base's (serial:PATH)")
    leader_port = leader_ports[0] if leader_ports else ""
    if leader_port and any(same_device(leader_port, port) for port in followers_ports):
        raise UserError(f"--leader serial:{leader_port}: the followers' link (--link) has that port, and a port is"
                        " one link's alone: give the leader base a port of its own")
    if args.radio_id is not None and not link_port and not getattr(args, "arena_radio", ""):
        raise UserError("--radio-id goes with --link serial:PATH (the radio this leader shares with others)")
    _check_radio_key(args, bool(link_port or getattr(args, "arena_radio", "")))
    camera: Rig | None
    if real:
        from app.files import load_calibration

        camera = load_calibration(args.calibration or config.calibration_path)
    else:
        camera = config.camera() if (args.feedback or config.feedback) == "vision" else None
    n_followers = scenario.n if scenario is not None else args.followers or config.followers
    return RunPlan(config, scenario, fleet_scenario, real, link if link_port else None,
                   leader if leader is not None and leader.scheme == "serial" else None, camera, n_followers,
                   scenario_name=args.scenario, camera_source=args.camera, camera_fps=args.camera_fps,
                   host=args.host, port=args.port, token=args.token, viewer_token=args.viewer_token,
                   rate_hz=args.rate, seed=args.seed, recordings=args.recordings, realtime=args.realtime,
                   loop_process=not getattr(args, "one_process", False),
                   reserve_cpu=getattr(args, "reserve_cpu", False), record=not args.no_record,
                   record_to=args.record, frames_hz=args.frames_hz, radio=_radio_plan(args),
                   fleet=_fleet_plan(args), ros2=ros2_plan(args, leader), foxglove=foxglove_plan(args))


def _radio_plan(args: argparse.Namespace) -> RadioPlan:
    from app.services.run import RadioPlan

    return RadioPlan(radio_id=args.radio_id, baud=args.baud, key=args.radio_key_bytes, sender=args.radio_sender,
                     allow_unauthenticated=args.allow_unauthenticated_radio, counter=args.radio_counter)


def _fleet_plan(args: argparse.Namespace) -> FleetPlan | None:
    if args.fleet is None:
        return None
    from app.services.run import FleetPlan

    return FleetPlan(args.fleet, args.leader_id, tuple(args.zenoh_listen), tuple(args.zenoh_connect), args.fleet_keys,
                     args.fleet_control, args.arena, getattr(args, "arena_radio", ""))


def _check_radio_key(args: argparse.Namespace, has_link: bool) -> None:
    """--radio-key, --radio-counter and --allow-unauthenticated-radio against the link; sets
    ``args.radio_key_bytes`` and ``args.radio_sender`` (one line on any mistake)."""
    args.radio_key_bytes, args.radio_sender = None, None
    if args.radio_key is None:
        if args.radio_counter is not None:
            raise UserError("--radio-counter goes with --radio-key")
        if args.radio_id is not None and not args.allow_unauthenticated_radio:
            raise UserError(f"--radio-id {args.radio_id}: a shared radio needs the fleet's radio key (--radio-key"
                            " DIR/radio/LEADER.radio, written by fleet-keys), or --allow-unauthenticated-radio")
        return
    if not has_link:
        raise UserError("--radio-key goes with --link serial:PATH (the robots' radio or cable)")
    from app.backends.radio_keys import load_leader_key

    key = load_leader_key(args.radio_key)
    if args.radio_id is not None and args.radio_id != key.radio_id:
        raise UserError(f"--radio-id {args.radio_id}: {args.radio_key} is radio id {key.radio_id}'s key")
    if args.radio_counter is not None:  # corrupt, unwritable or used up: said now, before anything is sent
        import time

        from app.backends.link_auth import FrameCounter
        from app.backends.radio_keys import check_counter_file

        check_counter_file(args.radio_counter, FrameCounter.clock_counter(time.time()))
    args.radio_key_bytes, args.radio_sender = key.key, key.radio_id


def _check_fleet_args(args: argparse.Namespace) -> FleetScenario | None:
    """The fleet's arguments (names, endpoints, an arena's leader id); the arena's scenario."""
    fleet_scenario = None
    if args.arena is not None:
        from app.files import load_fleet

        if args.scenario or args.camera or args.followers or args.leader:
            raise UserError("--arena leads the arena's robots: it cannot be combined with --scenario, --camera,"
                            " --leader or --followers")
        fleet_scenario = load_fleet(args.arena)
        ids = [ld.id for ld in fleet_scenario.leaders]
        if args.leader_id not in ids:
            raise UserError(f"--arena {args.arena}: --leader-id must be one of its leaders: {', '.join(ids)}"
                            + (f" (got {args.leader_id!r})" if args.leader_id else ""))
        args.fleet = args.fleet or fleet_scenario.name
        args.arena_radio = _arena_radio(args, ids.index(args.leader_id) + 1)
    fleet_args = (args.leader_id, args.zenoh_listen, (args.zenoh_connect or args.keys) and not args.ros2, args.fleet_control)
    if args.fleet is None and any(fleet_args):
        raise UserError("--leader-id, --zenoh-listen, --zenoh-connect, --keys and --fleet-control go with --fleet NAME")
    if args.fleet is not None:
        from app.cli.fleet import fleet_keys
        from app.fleet.bridge import check_endpoint, check_name

        try:
            check_name(args.fleet, "--fleet")
            check_name(args.leader_id or "", "--leader-id")
        except ValueError as exc:
            raise UserError(str(exc)) from None
        args.fleet_keys = fleet_keys(args.keys, args.leader_id, args.fleet)
        try:
            for endpoint in (*args.zenoh_listen, *args.zenoh_connect):
                check_endpoint(endpoint, args.fleet_keys)
        except ValueError as exc:
            raise UserError(str(exc)) from None
    return fleet_scenario


def _arena_radio(args: argparse.Namespace, number: int) -> str:
    """With ``--arena``, ``--link serial:PTY`` is this leader's radio (`arena --radio` prints one
    per leader): the robots are commanded over it, the arena gives the world. The leader's radio
    id is its place among the arena's leaders (given, it must be that). "": no radio."""
    from app.backends.links import FOLLOWERS, parse_link

    if args.link is None:
        if args.radio_id is not None:
            raise UserError("--radio-id goes with --link serial:PATH (the radio this leader shares with others)")
        return ""
    try:
        link = parse_link(args.link, FOLLOWERS)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    port = link.ports[0] if len(link.ports) == 1 else ""
    if not port:
        raise UserError(f"--arena with --link {args.link!r}: the link is this leader's radio, one serial:PATH"
                        " (`omniformation arena FLEET --radio` prints one per leader)")
    if args.radio_id is not None and args.radio_id != number:
        raise UserError(f"--radio-id {args.radio_id}: on {args.arena}'s radio {args.leader_id} is radio id {number}"
                        " (its place among the arena's leaders); leave --radio-id out")
    args.radio_id, args.link = number, None  # the arena team drives the radio, not the simulated team's link
    return port


def _say_where(args: argparse.Namespace, plan: RunPlan, service: Service, link: FollowerLink | None) -> None:
    if plan.real:
        source = f"the vision pipeline on camera {args.camera}"
    else:
        source = "the vision pipeline on the synthetic camera" if plan.camera else "the simulator's poses plus noise"
    port_name = getattr(link, "port_name", None)
    via = f"; followers on serial {port_name}" if port_name else "; observe only (no link)" if plan.real else ""
    print(f"omniformation: dashboard at {service.url}  (poses from {source}{via}; Ctrl-C to stop)", flush=True)
    print(f"omniformation: view only (watch and STOP, nothing else) at {service.viewer_url}", flush=True)
    if args.realtime:
        import time

        deadline = time.monotonic() + 5.0
        while service.loop.tick_count == 0 and time.monotonic() < deadline and not service.loop.stopping:
            time.sleep(0.02)  # the loop asks when its thread starts
        print(f"omniformation: --realtime: the loop is scheduled {service.loop.priority}", flush=True)
