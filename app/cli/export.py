"""`omniformation export FILE.mcap --ros2 DIR`: a recording for other tools (a ROS 2 bag,
app.recording.ros2_bag)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from app.cli.args import Parser
from app.files import UserError, display_path


def register(sub: "argparse._SubParsersAction[Parser]") -> None:
    ex = sub.add_parser("export", help="write a recording as a ROS 2 bag",
                        description="Write a recording as a rosbag2 folder (MCAP storage, CDR, ROS 2 Jazzy types):"
                                    " /tf, followers and slots (PoseArray), each follower's error and command, the"
                                    " leader's /cmd_vel and the camera frames, stamped with the session's time."
                                    " A damaged recording exports what can be read and says what was lost.")
    ex.add_argument("file", type=Path, help="a recording (.mcap)")
    ex.add_argument("--ros2", type=Path, required=True, metavar="DIR", help="the bag folder to write (must not exist)")
    ex.add_argument("--overwrite", action="store_true", help="replace DIR if it is a ROS 2 bag already")
    ex.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    from app.cli.sessions import load_recording
    from app.recording.ros2_bag import BagRefused, check_target, export_ros2

    try:
        check_target(args.ros2, args.overwrite)  # the arguments first: no need to read a large file to refuse them
    except BagRefused as exc:
        raise UserError(str(exc)) from None
    rec = load_recording(args.file)  # says on stderr what the recording lost
    try:
        result = export_ros2(rec, args.ros2, args.overwrite,
                             lambda done, total: print(f"  [{done}/{total}] ticks", flush=True))
    except BagRefused as exc:
        raise UserError(str(exc)) from None
    except OSError as exc:
        raise UserError(f"--ros2 {args.ros2}: cannot write: {exc.strerror or exc}") from None
    finally:
        rec.close()
    lost = f"; {result.unreadable} ticks or frames could not be read" if result.unreadable else ""
    print(f"wrote {display_path(args.ros2)}: {result.ticks} ticks, {result.frames} camera frames,"
          f" {sum(result.counts.values())} messages on {len(result.counts)} topics{lost}", flush=True)
    if result.loss or result.unreadable:
        print("omniformation: the bag holds what the recording still had; see above for what was lost",
              file=sys.stderr, flush=True)
    return 0
