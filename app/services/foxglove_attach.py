"""A session served to Foxglove (app.services.foxglove_live; docs/foxglove.md), attached to what
shows it: the live service, a replay, or the fleet page. The command line checks the flags
(app.cli.foxglove_args) and hands over a :class:`FoxglovePlan`."""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from app.files import UserError

Say = Callable[[str], None]


@dataclass(frozen=True)
class FoxglovePlan:
    """Where to serve (host, port; 0 = any free port) and the TLS certificate and key (PEM) or None."""

    host: str
    port: int
    tls: tuple[bytes, bytes] | None = None


class BehindDoor:
    """A Foxglove server (FoxgloveLive or FoxgloveFleet) on 127.0.0.1 behind the door clients reach
    (app.services.foxglove_relay, as `run --foxglove` serves): either subprotocol name, a client that
    does not read disconnected, TLS at the door. Everything else is the server's."""

    def __init__(self, make: Callable[[], Any], plan: FoxglovePlan) -> None:
        import ssl

        from app.dashboard.gate import is_loopback
        from app.services.foxglove_live import FoxgloveRefused, _bind_line
        from app.services.foxglove_relay import STALL_S, Relay

        if plan.tls is None and not is_loopback(plan.host):
            raise UserError(f"--foxglove {plan.host}:{plan.port}: serving off this machine needs TLS: give"
                            " --foxglove-tls-cert CERT.pem and --foxglove-tls-key KEY.pem (or serve on 127.0.0.1)")
        try:
            self.server = make()
        except FoxgloveRefused as exc:
            raise UserError(str(exc)) from None
        try:
            self.door = Relay(plan.host, plan.port, self.server.port, plan.tls, STALL_S)
        except (OSError, ssl.SSLError, ValueError) as exc:
            self.server.close()
            errno = getattr(exc, "errno", None) if not isinstance(exc, ssl.SSLError) else None
            why = RuntimeError(f"(os error {errno})" if errno in (98, 99) else f"TLS: {getattr(exc, 'reason', None) or exc}"
                               if isinstance(exc, (ssl.SSLError, ValueError)) else str(exc))
            raise UserError(_bind_line(plan.host, plan.port, why)) from None
        # the address people are given (and the status line names) is the door's
        self.server.host, self.server.port = plan.host, self.door.port
        self.server.scheme = "wss" if plan.tls else "ws"

    def __getattr__(self, name: str) -> Any:
        return getattr(self.server, name)

    def close(self) -> None:
        self.door.close()
        self.server.close()


def serve_foxglove(plan: FoxglovePlan | None, say: Say, subscribe: Callable[[Callable[..., None]], None] | None = None,
                   **kwargs: Any) -> Any:
    """The Foxglove server the plan asks for (None without one), behind the door, its ``on_tick``
    handed to ``subscribe``; ``kwargs`` go to FoxgloveLive (start_ns, params, time_of)."""
    if plan is None:
        return None
    from app.services.foxglove_live import FoxgloveLive

    live = BehindDoor(lambda: FoxgloveLive("127.0.0.1", 0, None, **kwargs), plan)
    if subscribe is not None:
        subscribe(live.on_tick)
    say(f"omniformation: Foxglove live at {live.url} (view only: docs/foxglove.md)")
    return live


def attach_to_service(plan: FoxglovePlan | None, service: Any, recorder: Any, stack: contextlib.ExitStack,
                      say: Say) -> None:
    """`run --foxglove`: the live service's ticks, parameter sets and step tests served to
    Foxglove with the recording's clock (its ``start_ns``), closed with the session. The server
    runs in a process of its own (FoxgloveProcess): no client can take the loop's CPU or time."""
    if plan is None:
        return
    from app.services.foxglove_live import FoxgloveRefused
    from app.services.foxglove_process import FoxgloveProcess

    try:
        live = FoxgloveProcess(plan.host, plan.port, plan.tls, params=service.store.get(),
                               start_ns=recorder.start_ns if recorder is not None else None,
                               rate_hz=service.loop.rate_hz)
    except FoxgloveRefused as exc:
        raise UserError(str(exc)) from None
    stack.callback(live.close)
    service.loop.subscribe(live.on_tick)
    service.store.subscribe(live.on_params)
    service.tests.listeners.append(live.on_trial)
    say(f"omniformation: Foxglove live at {live.url} (view only: docs/foxglove.md)")


def serve_replay(plan: FoxglovePlan | None, rec: Any, say: Say) -> Any:
    """`replay --foxglove`: the ticks the replay shows, at the recording's own times (its
    ``start_ns`` and each tick's session time), so Foxglove's clock is the recording's."""
    if plan is None:
        return None
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
    return serve_foxglove(plan, say, start_ns=start_ns, params=params, time_of=time_of)


class _Both:
    """The fleet page's sink for bus messages: the fleet recording and Foxglove live, either or both."""

    def __init__(self, *sinks: Any) -> None:
        self.sinks = [s for s in sinks if s is not None]

    def write(self, topic: str, msg: dict[str, Any]) -> None:
        for s in self.sinks:
            s.write(topic, msg)

    def status(self) -> str:
        return "; ".join(s.status() for s in self.sinks)


def serve_fleet(plan: FoxglovePlan | None, recorder: Any, say: Say) -> tuple[Any, Any]:
    """`fleet --foxglove`: (the sink the fleet page writes to, the Foxglove server or None)."""
    if plan is None:
        return recorder, None
    from app.services.foxglove_live import FoxgloveFleet

    live = BehindDoor(lambda: FoxgloveFleet("127.0.0.1", 0, None), plan)
    say(f"omniformation: Foxglove live at {live.url} (view only: docs/foxglove.md)")
    return _Both(recorder, live), live
