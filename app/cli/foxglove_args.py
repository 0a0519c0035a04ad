"""`--foxglove [HOST:]PORT` for `run`, `replay` and `fleet`: the session served to Foxglove
(app.services.foxglove_attach; docs/foxglove.md). One place for the flags and their checks, so
the three commands refuse alike: a host off this machine without TLS, a certificate that cannot
be read, a port in use: one line, exit 2."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.files import UserError, read_regular

if TYPE_CHECKING:
    from app.services.foxglove_attach import FoxglovePlan


def endpoint(text: str) -> tuple[str, int]:
    """An argparse type: ``PORT`` or ``HOST:PORT`` (``[V6]:PORT``); 0 = any free port."""
    host, sep, port_text = text.rpartition(":")
    host = host.strip("[]") if sep else "127.0.0.1"
    try:
        port = int(port_text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not [HOST:]PORT (e.g. 8765 or 127.0.0.1:8765)") from None
    if not 0 <= port <= 65535 or (sep and not host):
        raise argparse.ArgumentTypeError(f"{text!r} is not [HOST:]PORT with a port in 0..65535 (0 = any free port)")
    return host, port


def add_foxglove_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--foxglove", type=endpoint, metavar="[HOST:]PORT",
                        help="also serve the session to Foxglove, view-only (host 127.0.0.1 unless given; any other"
                             " host needs --foxglove-tls-cert and --foxglove-tls-key); see docs/foxglove.md")
    parser.add_argument("--foxglove-tls-cert", type=Path, metavar="CERT.pem", help="--foxglove: the server's certificate (PEM)")
    parser.add_argument("--foxglove-tls-key", type=Path, metavar="KEY.pem", help="--foxglove: its private key (PEM, PKCS#8)")


def _tls(args: argparse.Namespace) -> tuple[bytes, bytes] | None:
    cert, key = args.foxglove_tls_cert, args.foxglove_tls_key
    if cert is None and key is None:
        return None
    if args.foxglove is None:
        raise UserError("--foxglove-tls-cert and --foxglove-tls-key go with --foxglove [HOST:]PORT")
    if cert is None or key is None:
        raise UserError("--foxglove-tls-cert and --foxglove-tls-key go together (a certificate and its key)")
    out = []
    for flag, path in (("--foxglove-tls-cert", cert), ("--foxglove-tls-key", key)):
        try:  # a regular file of at most 64 KiB: a FIFO or /dev/zero is one line, not a hang
            data = read_regular(path, "a PEM file")
        except OSError as exc:
            raise UserError(f"{flag} {path}: cannot be read ({exc.strerror or exc})") from None
        except UserError as exc:
            raise UserError(f"{flag}: cannot be read: {exc}") from None
        if b"-----BEGIN " not in data:
            raise UserError(f"{flag} {path}: not a PEM file (expected -----BEGIN ...)")
        out.append(data)
    return out[0], out[1]


def check_foxglove_args(args: argparse.Namespace) -> None:
    """The flags alone, before anything opens: TLS files readable, TLS off loopback."""
    from app.dashboard.gate import is_loopback

    tls = _tls(args)
    if args.foxglove is not None and tls is None and not is_loopback(args.foxglove[0]):
        host, port = args.foxglove
        raise UserError(f"--foxglove {host}:{port}: serving off this machine needs TLS: give --foxglove-tls-cert"
                        " CERT.pem and --foxglove-tls-key KEY.pem (or serve on 127.0.0.1)")


def foxglove_plan(args: argparse.Namespace) -> FoxglovePlan | None:
    """The flags, checked (whether or not --foxglove is given: its TLS flags alone are refused), as
    the services take them (None without --foxglove)."""
    check_foxglove_args(args)
    if getattr(args, "foxglove", None) is None:
        return None
    from app.services.foxglove_attach import FoxglovePlan

    host, port = args.foxglove
    return FoxglovePlan(host, port, _tls(args))


def say(text: str) -> None:
    print(text, flush=True)


def serve_replay(args: argparse.Namespace, rec: Any) -> Any:
    """`replay --foxglove`: the recording's ticks served at their recorded times (app.services.foxglove_attach)."""
    from app.services.foxglove_attach import serve_replay as serve

    return serve(foxglove_plan(args), rec, say)


def serve_fleet(args: argparse.Namespace, recorder: Any) -> tuple[Any, Any]:
    """`fleet --foxglove`: (the sink the fleet page writes to, the Foxglove server or None)."""
    from app.services.foxglove_attach import serve_fleet as serve

    return serve(foxglove_plan(args), recorder, say)
