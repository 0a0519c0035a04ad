"""`omniformation arena`: the shared world of a fleet (paper §6) on the Zenoh bus."""

from __future__ import annotations

from typing import TYPE_CHECKING

import argparse
import json
import sys
from pathlib import Path

from app.cli.args import Parser, float_in, int_in, port, probability, token_arg
from app.files import UserError

if TYPE_CHECKING:

    from app.fleet.security import FleetKeys


def add_bus_args(p: argparse.ArgumentParser, prefix: str = "") -> None:
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"{prefix}an endpoint to listen on (repeatable; this process then forwards between those"
                        " that connect to it): tls/HOST:PORT with --keys, else tcp/127.0.0.1:PORT (loopback only)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT",
                   help=f"{prefix}an endpoint to connect to (repeatable); nothing is discovered by itself")
    p.add_argument("--keys", type=Path, metavar="DIR",
                   help=f"{prefix}this identity's bundle of the fleet's keys (`omniformation fleet-keys DIR` writes"
                        " DIR/ID/): mutual TLS and access control by identity; without them the bus stays on loopback")


def fleet_keys(keys_dir: Path | None, identity: str, fleet: str) -> FleetKeys | None:
    """``--keys DIR`` checked for this identity and fleet (one line naming the file, else)."""
    if keys_dir is None:
        return None
    from app.fleet.security import KeyFileError, load_fleet_keys

    try:
        return load_fleet_keys(keys_dir, identity, fleet)
    except KeyFileError as exc:
        raise UserError(str(exc)) from None


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    arena = sub.add_parser(
        "arena",
        help="simulate one world for every leader of a fleet (docs/fleet-protocol.md)",
        description="Step every leader and robot of a fleet scenario, publish the truth on the Zenoh bus, take"
                    " each leader's commands for the robots it owns, and grant orphans to the leaders that claim"
                    " them. Leaders join with `omniformation run --arena FLEET --leader-id ID`.",
    )
    arena.add_argument("fleet_scenario", metavar="FLEET", help="a fleet scenario: a name in static_config/fleets/ or a .toml")
    arena.add_argument("--fleet", metavar="NAME", help="the fleet's name on the bus (default: the scenario's name)")
    add_bus_args(arena)
    arena.add_argument("--minutes", type=float_in(0.0, 7 * 24 * 60.0, "min"),
                       help="stop after this long (default: until Ctrl-C)")
    arena.add_argument("--status-every", type=float_in(0.0, 3600.0, "s", lo_inclusive=True), default=5.0,
                       help="print a status line this often (s, default 5; 0: never)")
    arena.add_argument("--radio", action="store_true",
                       help="the robots take commands over an emulated radio, not the bus: one pty per leader is"
                            " printed (`run --arena FLEET --leader-id ID --link serial:PTY`); the arena is only the"
                            " world, the robots say who owns them (docs/fleet-protocol.md, Real robots)")
    arena.add_argument("--radio-drop", type=probability, default=0.0, metavar="P",
                       help="with --radio: the share of frames the radio loses (default 0)")
    arena.add_argument("--radio-delay-ms", type=float_in(0.0, 2000.0, "ms", lo_inclusive=True), default=0.0,
                       metavar="D", help="with --radio: how late the radio delivers a frame (default 0)")
    arena.add_argument("--radio-key", type=Path, metavar="ROBOTS.json",
                       help="with --radio: the fleet's radio keys the robots hold (fleet-keys writes"
                            " DIR/radio/robots.json; default: the open key)")
    arena.add_argument("--summary", type=Path, metavar="FILE.json",
                       help="write the arena's counts and the robots' owners here when it stops")
    arena.set_defaults(func=cmd_arena)

    page = sub.add_parser(
        "fleet",
        help="serve one page for a whole fleet: every team live, per-team controls, fleet-wide STOP",
        description="Follow every leader of a fleet on the Zenoh bus (and the arena, when one runs) in one viser"
                    " page; its controls reach each leader over the bus (docs/fleet-protocol.md).",
    )
    page.add_argument("--fleet", metavar="NAME", required=True, help="the fleet's name on the bus")
    add_bus_args(page)
    page.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1; others need the token)")
    page.add_argument("--port", type=port, default=8090, help="port (default 8090, 0 = any free port)")
    page.add_argument("--token", type=token_arg, help="the token browsers must present on a non-loopback --host")
    page.add_argument("--viewer-token", type=token_arg,
                      help="the token of a view-only URL (it may press STOP, nothing else; default: made up, printed)")
    page.add_argument("--record", type=Path, metavar="FILE.mcap",
                      help="record the whole fleet (a channel per leader) into this new file")
    from app.cli.foxglove_args import add_foxglove_args

    add_foxglove_args(page)
    page.set_defaults(func=cmd_fleet)

    keys = sub.add_parser(
        "fleet-keys",
        help="make a fleet's keys: a CA and a certificate per identity (arena, page, each leader)",
        description="Write DIR/ca/ (the fleet's certificate authority: ca.key and ca.pem, for the operator's machine"
                    " only) and, for the arena, the page and every leader, a bundle DIR/ID/ (ca.pem, fleet.json,"
                    " ID.pem and ID.key; the certificate's common name is the identity; folders 0700, keys 0600)."
                    " Copy DIR/ID/ to the machine that runs ID and start it with --keys pointing there"
                    " (docs/fleet-protocol.md, Security).",
    )
    keys.add_argument("dir", type=Path, metavar="DIR", help="where to write them (made if missing)")
    keys.add_argument("--fleet", metavar="NAME", required=True, help="the fleet's name on the bus")
    keys.add_argument("--leaders", metavar="L1,L2,...", required=True, help="the leader ids, comma-separated")
    keys.add_argument("--days", type=int_in(1, 3650), default=365, help="how long the certificates are valid (days,"
                                                                         " default 365)")
    keys.add_argument("--ros2", action="store_true", help="also a bundle DIR/ros2/ for the ROS 2 machines (their Zenoh"
                                                          " router, a ROS base; docs/ros2.md)")
    keys.add_argument("--ros2-control-by", metavar="ID,...", default="ros2",
                      help="with --ros2: the identities the ROS 2 router (DIR/ros2/router.json5) lets publish"
                           " /omniformation/stop and /omniformation/goal (default: ros2, the operator's ROS tools)")
    keys.add_argument("--overwrite", action="store_true", help="replace keys already in DIR (a new CA: every"
                                                               " identity needs its new files)")
    keys.set_defaults(func=cmd_fleet_keys)


def cmd_fleet_keys(args: argparse.Namespace) -> int:
    from app.fleet.bridge import check_name
    from app.fleet.security import make_fleet_keys, parse_leaders

    try:
        check_name(args.fleet, "--fleet")
        leaders = parse_leaders(args.leaders)
        controllers = tuple(c.strip() for c in args.ros2_control_by.split(","))
        if args.ros2:
            from app.fleet.security import Roster, check_ros2_controllers

            check_ros2_controllers(Roster(args.fleet, leaders, True), controllers)
        elif args.ros2_control_by != "ros2":
            raise ValueError("--ros2-control-by goes with --ros2 (the ROS 2 machines' router)")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if args.dir.exists() and not args.dir.is_dir():
        raise UserError(f"{args.dir}: not a directory")
    from app.backends.radio_keys import check_radio_keys_writable

    try:  # everything the radio needs is checked before the first file is written
        check_radio_keys_writable(args.dir / "radio", leaders, overwrite=args.overwrite)
    except (FileExistsError, ValueError) as exc:
        raise UserError(str(exc)) from None
    try:
        written = make_fleet_keys(args.dir, args.fleet, leaders, overwrite=args.overwrite, days=args.days,
                                  ros2=args.ros2, ros2_control_by=controllers)
    except FileExistsError as exc:
        raise UserError(str(exc)) from None
    except OSError as exc:
        raise UserError(f"{args.dir}: cannot write keys ({exc.strerror or exc})") from None
    print(f"omniformation: fleet {args.fleet}: {len(written)} files in {args.dir} (identities: arena, page,"
          f" {', '.join(leaders)}{', ros2' if args.ros2 else ''}; valid {args.days} days)", flush=True)
    print(f"omniformation: copy {args.dir}/ID/ to the machine that runs ID and give it --keys there; keep"
          f" {args.dir}/ca/ (the CA's private key) on the operator's machine only", flush=True)
    write_fleet_radio_keys(args.dir, leaders, args.overwrite)
    return 0


def write_fleet_radio_keys(directory: Path, leaders: tuple[str, ...], overwrite: bool) -> None:
    """The fleet's radio key beside its certificates: DIR/radio/robots.json and DIR/radio/ID.radio
    (app.backends.radio_keys; docs/follower-protocol.md, "Keys and provisioning")."""
    from app.backends.radio_keys import copy_into_bundles, write_radio_keys

    radio = directory / "radio"
    try:
        copy_into_bundles(write_radio_keys(radio, leaders, overwrite=overwrite), directory)
    except (FileExistsError, ValueError) as exc:
        raise UserError(str(exc)) from None
    except OSError as exc:
        raise UserError(f"{radio}: cannot write the radio key ({exc.strerror or exc})") from None
    ids = ", ".join(f"{name} {k + 1}" for k, name in enumerate(leaders))
    print(f"omniformation: radio key in {radio} (radio ids: {ids}); each leader's ID.radio is in its bundle too"
          f" (--radio-key DIR/ID/ID.radio); the robots get robots.json through `omniformation radio-provision`",
          flush=True)


def cmd_arena(args: argparse.Namespace) -> int:
    """The arena: check everything into a plan, then app.services.arena runs it; status lines here."""
    import signal
    import time

    from app.files import load_fleet
    from app.fleet.bridge import check_name
    from app.keys import root
    from app.services.arena import ArenaPlan, run_arena

    scenario = load_fleet(args.fleet_scenario)
    fleet = args.fleet or scenario.name
    try:
        check_name(fleet, "--fleet" if args.fleet else f"{args.fleet_scenario}: name")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    if not args.radio and (args.radio_drop or args.radio_delay_ms):
        raise UserError("--radio-drop and --radio-delay-ms go with --radio")
    if args.radio_key is not None and not args.radio:
        raise UserError("--radio-key goes with --radio")
    from app.backends.emulator import robot_auth

    radio_auth = robot_auth(args.radio_key) if args.radio_key is not None else None
    plan = ArenaPlan(scenario, fleet, tuple(args.zenoh_listen), tuple(args.zenoh_connect),
                     fleet_keys(args.keys, "arena", fleet), args.radio, args.radio_drop, args.radio_delay_ms / 1000.0,
                     radio_auth)
    with run_arena(plan) as running:
        arena, stop = running.arena, running.stop
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
        print(f"omniformation: arena {fleet}: {len(scenario.leaders)} leaders, {scenario.robots} robots at"
              f" {scenario.rate_hz:g} Hz; truth on {root(fleet)}/arena/truth (Ctrl-C to stop)", flush=True)
        if arena.radio is not None:
            for i, (lid, path) in enumerate(zip(arena.ids, arena.radio.paths)):
                print(f"radio {lid}: {path} (radio id {i + 1})", flush=True)
        start = time.monotonic()
        while not stop.is_set():
            stop.wait(args.status_every if args.status_every > 0 else 1.0)
            if args.minutes is not None and time.monotonic() - start >= args.minutes * 60:
                stop.set()
            if args.status_every > 0 and not stop.is_set():
                c = arena.counts
                print(f"  t {arena.t:7.1f} s  alive {' '.join(sorted(arena.alive)) or '-'}  conflicts {c.conflicts}"
                      f"  watchdog stops {c.watchdog_stops}  claims {c.claims_granted} granted,"
                      f" {c.claims_refused} refused  malformed {c.malformed}  two owners {arena.two_owners}"
                      f"  closest {arena.gap_m * 100:.0f} cm"
                      f" (contacts {c.contacts})", flush=True)
    if args.summary is not None:
        args.summary.write_text(json.dumps(running.summary, indent=1) + "\n")
    c = arena.counts
    print(f"omniformation: arena stopped after {arena.t:.1f} s: conflicts {c.conflicts}, watchdog stops"
          f" {c.watchdog_stops}, claims {c.claims_granted} granted / {c.claims_refused} refused"
          f" / {c.claims_repeated} repeated, closest two bodies"
          f" {c.closest_m * 100:.0f} cm apart (closer than 0.25 m: {c.contacts} steps)", flush=True)
    return 0


def cmd_fleet(args: argparse.Namespace) -> int:
    """The fleet page: check everything into a plan, then app.services.fleet_page serves it."""
    import signal
    import threading

    from app.cli.foxglove_args import check_foxglove_args, foxglove_plan
    from app.dashboard.gate import is_loopback
    from app.files import check_new_file, display_path
    from app.fleet.bridge import check_name
    from app.services.fleet_page import FleetPagePlan, serve_fleet_page

    try:
        check_name(args.fleet, "--fleet")
    except ValueError as exc:
        raise UserError(str(exc)) from None
    check_foxglove_args(args)
    if args.record is not None:
        check_new_file(args.record, "recording", ".mcap")
        if args.record.exists():
            raise UserError(f"{args.record}: exists; a recording is never written over another (give a new name)")
    if args.viewer_token is not None and args.viewer_token == args.token:
        raise UserError("--viewer-token: must differ from --token (a viewer may not command the fleet)")
    plan = FleetPagePlan(args.fleet, tuple(args.zenoh_listen), tuple(args.zenoh_connect),
                         fleet_keys(args.keys, "page", args.fleet), args.host, args.port, args.token,
                         args.viewer_token, args.record, foxglove_plan(args))
    with serve_fleet_page(plan, lambda text, err=False: print(text, flush=True)) as running:
        gate, recorder = running.gate, running.recorder
        stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
        if not is_loopback(args.host):
            print(f"omniformation: serving on {args.host}: only browsers that open the URL below (it carries the"
                  " token) may see and command the fleet", file=sys.stderr)
        print(f"omniformation: fleet {args.fleet} at {gate.url}  (Ctrl-C to stop)", flush=True)
        print(f"omniformation: view only (watch and STOP, nothing else) at {gate.viewer_url}", flush=True)
        if recorder is not None:
            print(f"omniformation: recording the fleet to {display_path(recorder.path)}", flush=True)
        stop.wait()
    if recorder is not None:
        print(f"omniformation: fleet recording finished: {display_path(recorder.path)} ({recorder.written}"
              " messages)", flush=True)
    return 0
