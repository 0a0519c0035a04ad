"""The `omniformation` command line: one subcommand per job, one module per family.

Every module here registers its subcommands the same way, ``register(sub)``, and each
subcommand runs a ``cmd_*(args) -> int`` of that module. The modules import only what
parsing needs, and the work's own modules inside ``cmd_*``, so that `--help` and argument
errors answer at once.

User mistakes (bad arguments, bad files) print one line and exit with code 2;
no traceback is shown for them.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from app.cli import bench, camera, emulator, export, fleet, live, ros2, sessions, simulate, study
from app.cli.args import EXIT_USAGE, Parser
from app.console import whole_lines
from app.files import UserError

FAMILIES = (simulate, study, live, fleet, camera, emulator, ros2, sessions, export, bench)


def build_parser() -> Parser:
    parser = Parser(
        prog="omniformation",
        description="Leader-follower formation control from one omnidirectional camera.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    for family in FAMILIES:
        family.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        with whole_lines():  # the loop's thread and the command's print lines at once (app.console)
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
