"""`run --foxglove`: Foxglove live (app.services.foxglove_live.FoxgloveLive) in a process of its
own, fed by the loop as the page's process is (docs/foxglove.md, docs/safety.md)."""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from app.params import Params
from app.refusals import REFUSALS
from app.recording.schema import IMAGE_TOPIC
from app.services.foxglove_live import DEFAULT_PORT, FoxgloveLive, FoxgloveRefused, _bind_line
from app.dashboard.gate import is_loopback
from app.tick import TickState

log = logging.getLogger(__name__)


READY_S = 120.0  # how long the loop's side waits for the Foxglove process to serve (imports on a loaded machine)


class FoxgloveProcess:
    """`run --foxglove`: :class:`FoxgloveLive` in a process of its own, fed by the loop as the
    page's process is (app.services.page_process, the same mechanism): the loop hands each state
    to a :class:`~app.tick.LatestStatePublisher`, whose thread sends the newest one down one pipe
    (pickled); a state superseded before it went is skipped there, so a Foxglove process that
    falls behind skips ticks and the loop never waits. Parameter sets and step tests are queued and
    go before the next state. The camera's frame travels only while a client subscribes to
    ``/camera/image`` (the process says when that changes) and only at ``frame_rate_hz``.

    Why: the SDK's server, the encoding of every message and every client's traffic (300 clients
    that never read, a flood of bad messages, the SDK's log lines about them) then run on the
    other core under another interpreter lock, in a session (autogroup) of its own: with the
    server in the loop's process, 300 silent clients took the loop from 30 to 23 Hz and skipped
    ticks. Closing: the process ends when the loop's side closes or its pipe breaks; if it dies,
    the session goes on without Foxglove (it commands nothing) and says so once."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, tls: tuple[bytes, bytes] | None = None,
                 frame_rate_hz: float = 10.0, start_ns: int | None = None, params: Params | None = None,
                 rate_hz: float = 30.0, stall_s: float | None = None) -> None:
        """``stall_s``: how long a client may leave its send buffer full before it is dropped
        (app.services.foxglove_relay.STALL_S by default)."""
        if tls is None and not is_loopback(host):
            raise FoxgloveRefused(f"--foxglove {host}:{port}: serving off this machine needs TLS: give"
                                  " --foxglove-tls-cert CERT.pem and --foxglove-tls-key KEY.pem (or serve on 127.0.0.1)")
        import multiprocessing

        from app.tick import LatestStatePublisher

        self.host = host
        self.scheme = "wss" if tls else "ws"
        self.frame_every = max(1, math.floor(rate_hz / frame_rate_hz + 0.5)) if frame_rate_hz > 0 else 0
        self.watching = False  # a client subscribes to the camera (the process says so)
        self.sent = 0  # states sent down the pipe
        self.frames_sent = 0
        self.gone = False  # the process ended (said once)
        self._frame_tick = -(10**9)
        self._outbox: deque[tuple[Any, ...]] = deque()
        self._send_lock = threading.Lock()
        ctx = multiprocessing.get_context("spawn")
        ours, theirs = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(target=foxglove_main, name="omniformation-foxglove", daemon=True,
                                 args=(theirs, host, port, tls, frame_rate_hz,
                                       time.time_ns() if start_ns is None else start_ns, params, stall_s))
        self._proc.start()
        theirs.close()
        self._conn = ours
        msg: tuple[Any, ...] = ("failed", "--foxglove: the Foxglove process did not start")
        try:
            if ours.poll(READY_S):
                msg = ours.recv()
        except (EOFError, OSError):
            pass
        if msg[0] != "ready":
            self._end()
            raise FoxgloveRefused(str(msg[1]))
        self.port = int(msg[1])
        self._sender = LatestStatePublisher(self._send, name="foxglove-sender")
        threading.Thread(target=self._listen, name="foxglove-listener", daemon=True).start()

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}"

    @property
    def pid(self) -> int:
        return int(self._proc.pid or 0)

    @property
    def skipped(self) -> int:
        """States superseded before they went (the Foxglove process was behind)."""
        return int(self._sender.skipped)

    # -- the loop, the store and the step tests (never wait) --------------------------------
    def on_tick(self, s: TickState) -> None:
        self._sender(s)

    def on_params(self, p: Params, source: str, notices: tuple[Any, ...]) -> None:
        self._outbox.append(("params", p, source))

    def on_trial(self, trial: Any) -> None:
        self._outbox.append(("trial", trial.payload()))

    # -- the sender's thread ----------------------------------------------------------------
    def _send(self, state: TickState) -> bool:
        if self.gone:
            return False
        if state.frame is not None:
            framed = self.watching and self.frame_every > 0 and (
                state.tick - self._frame_tick >= self.frame_every or state.tick < self._frame_tick)
            pixels = np.ascontiguousarray(np.asarray(state.frame)) if framed else None  # a synthetic frame renders here
            state = dataclasses.replace(state, frame=pixels)
            if framed:
                self._frame_tick = state.tick
                self.frames_sent += 1
        try:
            with self._send_lock:
                while self._outbox:
                    self._conn.send(self._outbox.popleft())
                self._conn.send(("tick", state))
            self.sent += 1
            return True
        except (OSError, ValueError):
            self._say_gone()
            return False

    def _listen(self) -> None:
        while True:
            try:
                msg = self._conn.recv()
            except (EOFError, OSError, ValueError):
                self._say_gone()
                return
            if msg[0] == "watch":
                self.watching = bool(msg[1])

    def _say_gone(self) -> None:
        if not self.gone and not getattr(self, "_closing", False):
            self.gone = True
            log.warning("Foxglove live: its process ended; the session goes on without it")

    def close(self) -> None:
        """Stop feeding, ask the process to end (it serves what it has), then make sure it has."""
        self._closing = True
        self._sender.close()
        with self._send_lock:
            try:
                self._conn.send(("close",))
            except (OSError, ValueError):
                pass
        self._end()

    def _end(self) -> None:
        self._proc.join(10.0)
        if self._proc.is_alive():
            self._proc.terminate()
            self._proc.join(5.0)
        self._conn.close()


def foxglove_main(conn: Any, host: str, port: int, tls: tuple[bytes, bytes] | None, frame_rate_hz: float,
                  start_ns: int, params: Params | None, stall_s: float | None = None) -> None:
    """The Foxglove process: FoxgloveLive serving what the loop's side sends (see FoxgloveProcess),
    the SDK on 127.0.0.1 behind the door the clients reach (app.services.foxglove_relay)."""
    import ssl

    from app.services.foxglove_relay import STALL_S, Relay

    import contextlib
    import os
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the loop's process to handle: it closes this one
    with contextlib.suppress(OSError):  # a session, hence an autogroup, of its own (as the page's: sched(7))
        os.setsid()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    try:
        live = FoxgloveLive("127.0.0.1", 0, None, frame_rate_hz=frame_rate_hz, start_ns=start_ns, params=params)
    except FoxgloveRefused as exc:
        conn.send(("failed", str(exc)))
        return
    try:
        door = Relay(host, port, live.port, tls, STALL_S if stall_s is None else stall_s)
    except (OSError, ssl.SSLError, ValueError) as exc:
        live.close()
        errno = getattr(exc, "errno", None) if not isinstance(exc, ssl.SSLError) else None
        why = RuntimeError(f"(os error {errno})" if errno in (98, 99) else f"TLS: {getattr(exc, 'reason', None) or exc}"
                           if isinstance(exc, (ssl.SSLError, ValueError)) else str(exc))
        conn.send(("failed", _bind_line(host, port, why)))
        return
    conn.send(("ready", door.port))
    image = live.channels[IMAGE_TOPIC]
    watching: bool | None = None
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):  # the loop's process is gone
                break
            if msg[0] == "close":
                break
            if msg[0] == "tick":
                live.on_tick(msg[1])
            elif msg[0] == "params":
                live.on_params(msg[1], msg[2], ())
            elif msg[0] == "trial":
                live.on_trial_payload(msg[1])
            now = image.has_sinks()
            if now != watching:
                watching = now
                with contextlib.suppress(OSError, ValueError):
                    conn.send(("watch", now))
    finally:
        door.close()
        live.close()
        REFUSALS.flush(final=True)  # the counts not said yet
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(0)
