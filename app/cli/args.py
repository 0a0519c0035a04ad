"""What every subcommand shares: the parser that refuses in one line, and the argument types
that name the allowed range (so every command refuses a bad value alike)."""

from __future__ import annotations

import argparse
import math
from typing import Any, NoReturn
from collections.abc import Callable

EXIT_USAGE = 2

ArgType = Callable[[str], object]
Subcommands = "argparse._SubParsersAction[Parser]"


class Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (and exit code 2)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def float_in(lo: float, hi: float, unit: str, lo_inclusive: bool = False) -> Callable[[str], float]:
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


def int_in(lo: int, hi: int, what: str = "") -> Callable[[str], int]:
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


seed = int_in(0, 2**32 - 1)
port = int_in(0, 65535, " (0 = any free port)")
probability = float_in(0.0, 1.0, "(a probability)", lo_inclusive=True)


def token_arg(text: str) -> str:
    """An argparse type: a dashboard token, 16 to 200 URL-safe characters."""
    import re

    if not re.fullmatch(r"[A-Za-z0-9_-]{16,200}", text):
        raise argparse.ArgumentTypeError("a token is 16 to 200 characters of A-Z, a-z, 0-9, _ and -")
    return text


def serve_page(make: Callable[[], Any], host: str, port: int, what: str, started: Callable[[Any], str]) -> int:
    """Serve a page until Ctrl-C or SIGTERM: ``make()`` builds the service (binding its port:
    a port taken or an address not here is one line, exit 2), a warning when it is served off
    loopback (``what``: what a browser with the token may do), the line ``started(svc)``."""
    import signal
    import sys

    from app.dashboard.gate import is_loopback
    from app.files import UserError, bind_error

    try:
        svc = make()
    except OSError as exc:
        raise UserError(bind_error(host, port, exc)) from None
    if not is_loopback(host):
        print(f"omniformation: serving on {host}: only browsers that open the URL below (it carries the token)"
              f" may {what}", file=sys.stderr)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: svc.stop())
    if hasattr(svc, "start"):
        svc.start()
    print(started(svc), flush=True)
    try:
        svc.wait()
    except KeyboardInterrupt:
        pass
    finally:
        svc.close()
    return 0
