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
    radio.set_defaults(func=cmd_radio)


def cmd_radio(args: argparse.Namespace) -> int:
    from app.backends.radio import run_radio

    return run_radio(args.leaders, args.followers, args.drop, args.delay_ms, args.seed, args.summary, args.minutes)


def cmd_emulate(args: argparse.Namespace) -> int:
    from app.backends.emulator import run_emulator

    return run_emulator(args)
