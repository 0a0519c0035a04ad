"""`omniformation emulate-follower`: emulated followers on a pseudo-terminal or a serial port
(the emulator itself is app.backends.emulator)."""

from __future__ import annotations

import argparse
from pathlib import Path

from app.cli.args import Parser, float_in, int_in, probability, seed
from core.link.protocol import MAX_FOLLOWER_ADDRESS


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    em = sub.add_parser(
        "emulate-follower", help="emulated followers on a pseudo-terminal (or a serial port)",
        description="Run emulated followers (differential drive, wheel encoders, the 0.5 s watchdog) that"
                    " speak docs/follower-protocol.md on a fresh pseudo-terminal (--pty, the default) or a"
                    " serial device (--port).")
    where = em.add_mutually_exclusive_group()
    where.add_argument("--pty", action="store_true", help="open a pseudo-terminal and print its path (default)")
    where.add_argument("--port", help="serve this serial device instead, e.g. /dev/ttyUSB0")
    em.add_argument("--link-path", type=Path, help="keep a symlink to the port at this path (stable across restarts)")
    em.add_argument("--followers", type=int_in(1, MAX_FOLLOWER_ADDRESS), default=3,
                    help="how many followers, at addresses 1..N (default 3)")
    em.add_argument("--leader", action="store_true",
                    help="emulate the leader base instead (address 0: its wheel odometry for eq. 38)")
    em.add_argument("--baud", type=int_in(1200, 4_000_000), default=115200, help="baud rate for --port (default 115200)")
    em.add_argument("--drop", type=probability, default=0.0, help="probability of dropping a reply (default 0)")
    em.add_argument("--corrupt", type=probability, default=0.0, help="probability of flipping a bit in a reply (default 0)")
    em.add_argument("--seed", type=seed, default=0, help="seed of --drop / --corrupt")
    em.add_argument("--radio-key", type=Path, metavar="ROBOTS.json",
                    help="the fleet's radio keys for the robots (fleet-keys writes DIR/radio/robots.json): they obey"
                         " only the fleet's leaders; default: the open key (any leader)")
    em.add_argument("--protocol", type=int, choices=(2, 3), default=3,
                    help="3 (default): authenticated frames; 2: older robots that know no key")
    em.set_defaults(func=cmd_emulate)

    radio = sub.add_parser(
        "radio", help="one emulated radio shared by several leaders: a pseudo-terminal per leader",
        description="Emulate one radio medium: every leader's link (a pseudo-terminal each, printed one per line)"
                    " reaches every follower (addresses 1..M; protocol 2 ownership, docs/follower-protocol.md),"
                    " and every reply reaches every leader; frames are lost with --drop and delivered --delay-ms"
                    " later.")
    radio.add_argument("--leaders", type=int_in(1, 16), default=2, help="leader links (default 2)")
    radio.add_argument("--followers", type=int_in(1, MAX_FOLLOWER_ADDRESS), default=3,
                       help="followers, at addresses 1..M (default 3)")
    radio.add_argument("--drop", type=probability, default=0.0, help="probability of losing a frame (default 0)")
    radio.add_argument("--delay-ms", type=float_in(0.0, 2000.0, "ms", lo_inclusive=True), default=0.0,
                       help="delivery delay of every frame (ms, default 0)")
    radio.add_argument("--seed", type=seed, default=0, help="seed of --drop")
    radio.add_argument("--minutes", type=float_in(0.0, 7 * 24 * 60.0, "min"), help="stop after this long")
    radio.add_argument("--summary", type=Path, metavar="FILE.json",
                       help="write each robot's owner and counts here when it stops")
    radio.add_argument("--radio-key", type=Path, metavar="ROBOTS.json",
                       help="the fleet's radio keys for the robots (fleet-keys writes DIR/radio/robots.json); default:"
                            " the open key (any leader)")
    radio.add_argument("--older-robots", type=addresses, default=(), metavar="A,B",
                       help="these robots speak protocol 2 only (no key), as older firmware does")
    radio.set_defaults(func=cmd_radio)

    prov = sub.add_parser(
        "radio-provision", help="what the robots' firmware needs: the fleet's radio key as a C header or a record",
        description="Turn DIR/radio/robots.json (written by fleet-keys) into what the robots are flashed with: a C"
                    " header defining OF_RADIO_AUTH for firmware/omni_follower.h (--header) and/or a binary record"
                    " (--record, read by firmware/host_sim.c --radio-record); --stop sets the robots' STOP policy"
                    " (docs/safety.md). Every file is written mode 0600.")
    prov.add_argument("robots", type=Path, metavar="ROBOTS.json", help="the robots' radio keys (DIR/radio/robots.json)")
    prov.add_argument("--header", type=Path, metavar="FILE.h", help="write the C header here")
    prov.add_argument("--record", type=Path, metavar="FILE.bin", help="write the binary record here")
    prov.add_argument("--stop", choices=("anyone", "authenticated"),
                      help="which STOP a robot obeys: anyone's (fail-safe, the default) or only an authenticated one")
    prov.set_defaults(func=cmd_provision)

    rot = sub.add_parser(
        "radio-rotate", help="rotate the fleet's radio key in two steps (robots accept both keys meanwhile)",
        description="--begin: a new key; the robots' record lists the current and the new key, the leaders' new"
                    " files are written to DIR/radio/next/. --finish: the robots accept only the new key and the"
                    " leaders' files are replaced (docs/follower-protocol.md, Rotating the key).")
    rot.add_argument("dir", type=Path, metavar="DIR/radio", help="the fleet's radio folder")
    step = rot.add_mutually_exclusive_group(required=True)
    step.add_argument("--begin", action="store_true", help="a new key: the robots' record lists both, the leaders'"
                                                            " new files go to DIR/radio/next/")
    step.add_argument("--finish", action="store_true", help="the robots accept only the new key; the leaders' files"
                                                             " and their bundles' copies are replaced")
    step.add_argument("--status", action="store_true", help="say where a rotation stands (and what to run next)")
    rot.set_defaults(func=cmd_rotate)


def addresses(text: str) -> tuple[int, ...]:
    try:
        out = tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: robot addresses 1..{MAX_FOLLOWER_ADDRESS}, comma-separated") \
            from None
    if not all(1 <= a <= MAX_FOLLOWER_ADDRESS for a in out):
        raise argparse.ArgumentTypeError(f"{text!r}: robot addresses 1..{MAX_FOLLOWER_ADDRESS}, comma-separated")
    return out


def cmd_radio(args: argparse.Namespace) -> int:
    from app.backends.emulator import robot_auth
    from app.backends.radio import run_radio

    return run_radio(args.leaders, args.followers, args.drop, args.delay_ms, args.seed, args.summary, args.minutes,
                     robot_auth(args.radio_key), args.older_robots)


def cmd_emulate(args: argparse.Namespace) -> int:
    from app.backends.emulator import run_emulator

    return run_emulator(args)


def cmd_provision(args: argparse.Namespace) -> int:
    from app.backends.radio_keys import load_robot_auth, set_stop_policy, write_provision
    from app.files import UserError

    if args.stop is not None:
        load_robot_auth(args.robots)
        set_stop_policy(args.robots, args.stop)
    auth = load_robot_auth(args.robots)
    try:
        written = write_provision(auth, args.header, args.record)
    except OSError as exc:
        raise UserError(f"cannot write the robots' provisioning ({exc.strerror or exc})") from None
    n_keys = len(auth.leader_keys[0]) if auth.leader_keys else len(auth.keys)
    mode = "a key per leader" if auth.leader_keys else "one key for the fleet"
    print(f"omniformation: robots provisioned: {n_keys} key(s), {mode}, leaders {list(auth.leaders)}, STOP from"
          f" {auth.stop}" + "".join(f"; {w}" for w in written), flush=True)
    return 0


def cmd_rotate(args: argparse.Namespace) -> int:
    from app.backends.radio_keys import rotate, rotation_state

    if args.status:
        print(f"omniformation: rotation of {args.dir}: {rotation_state(args.dir).describe()}", flush=True)
        return 0
    written = rotate(args.dir, finish=args.finish)  # the leaders' bundles (fleet-keys' DIR/ID/) too
    step = ("finished: provision the robots again (only the new key now); the leaders already sign with it"
            if args.finish else "begun: provision the robots (they accept both keys), then give each leader"
                                " its file from next/ and restart it, then --finish")
    print(f"omniformation: rotation {step} ({len(written)} files)", flush=True)
    return 0
