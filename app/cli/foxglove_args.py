"""`--foxglove [HOST:]PORT` for `run`, `replay` and `fleet`: the session served to Foxglove
(app.services.foxglove_live; docs/foxglove.md). One place for the flags and their checks, so
the three commands refuse alike: a host off this machine without TLS, a certificate that cannot
be read, a port in use: one line, exit 2."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from app.files import UserError

if TYPE_CHECKING:
    from app.services.foxglove_live import FoxgloveLive


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
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise UserError(f"{flag} {path}: cannot be read ({exc.strerror or exc})") from None
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


def serve_foxglove(args: argparse.Namespace, subscribe: Callable[[Callable[..., None]], None] | None = None,
                   **kwargs: Any) -> FoxgloveLive | None:
    """The Foxglove server the flags ask for (None without --foxglove), its ``on_tick`` handed
    to ``subscribe``; ``kwargs`` go to FoxgloveLive (start_ns, params, time_of)."""
    if getattr(args, "foxglove", None) is None:
        return None
    check_foxglove_args(args)
    from app.services.foxglove_live import FoxgloveLive, FoxgloveRefused

    host, port = args.foxglove
    try:
        live = FoxgloveLive(host, port, _tls(args), **kwargs)
    except FoxgloveRefused as exc:
        raise UserError(str(exc)) from None
    if subscribe is not None:
        subscribe(live.on_tick)
    print(f"omniformation: Foxglove live at {live.url} (view only: docs/foxglove.md)", file=sys.stdout, flush=True)
    return live


def attach_to_service(args: argparse.Namespace, service: Any, recorder: Any, stack: Any) -> None:
    """`run --foxglove`: the live service's ticks, parameter sets and step tests served to
    Foxglove with the recording's clock (its ``start_ns``), closed with the session."""
    live = serve_foxglove(args, service.loop.subscribe, params=service.store.get(),
                          start_ns=recorder.start_ns if recorder is not None else None)
    if live is not None:
        service.store.subscribe(live.on_params)
        service.tests.listeners.append(live.on_trial)
        stack.callback(live.close)


def serve_replay(args: argparse.Namespace, rec: Any) -> FoxgloveLive | None:
    """`replay --foxglove`: the ticks the replay shows, at the recording's own times (its
    ``start_ns`` and each tick's session time), so Foxglove's clock is the recording's."""
    import numpy as np

    try:
        start_ns = int(rec.metadata.get("start_ns", "0") or 0)
    except ValueError:
        start_ns = 0
    numbers, times = rec.tick_numbers, rec.t

    def time_of(s: Any) -> float:
        k = int(np.clip(np.searchsorted(numbers, s.tick), 0, len(times) - 1))
        return float(times[k])

    params = None
    if rec.params:
        from app.recording.reader import params_from_recording

        params = params_from_recording(rec)
    return serve_foxglove(args, start_ns=start_ns, params=params, time_of=time_of)


class _Both:
    """The fleet page's sink for bus messages: the fleet recording and Foxglove live, either or both."""

    def __init__(self, *sinks: Any) -> None:
        self.sinks = [s for s in sinks if s is not None]

    def write(self, topic: str, msg: dict[str, Any]) -> None:
        for s in self.sinks:
            s.write(topic, msg)

    def status(self) -> str:
        return "; ".join(s.status() for s in self.sinks)


def serve_fleet(args: argparse.Namespace, recorder: Any) -> tuple[Any, Any]:
    """`fleet --foxglove`: (the sink the fleet page writes to, the Foxglove server or None)."""
    if getattr(args, "foxglove", None) is None:
        return recorder, None
    check_foxglove_args(args)
    from app.services.foxglove_live import FoxgloveFleet, FoxgloveRefused

    host, port = args.foxglove
    try:
        live = FoxgloveFleet(host, port, _tls(args))
    except FoxgloveRefused as exc:
        raise UserError(str(exc)) from None
    print(f"omniformation: Foxglove live at {live.url} (view only: docs/foxglove.md)", flush=True)
    return _Both(recorder, live), live
