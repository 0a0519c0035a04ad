"""The page in a process of its own (`run`'s default; `run --one-process` keeps it in the loop's):
the loop's process keeps the loop, the link, the recorder and the one ParamsStore; the page's
process (viser server, gate, dashboard) is a client of the loop's state over one pipe.

Why: viser encodes every scene update and decodes every client's message under the same
interpreter lock as the loop; a flood of client messages took the loop's time. Here the page's
work runs on the other core.

The channel, one pipe, pickled messages (docs/safety.md, "The page in a process of its own"):

* loop -> page: ``("tick", TickState, Params | None, lines | None, skipped)``, the newest tick only (a slow page
  skips ticks, the loop never waits for it), with the parameters in force whenever they changed;
  with no browser on the page, one tick in ``UNWATCHED_EVERY`` (its charts and health rules need no
  more, and several unwatched leaders share a machine), carrying the longest frame-to-command of
  the ticks it stands for (the health rule's per-tick alarm misses none of them).
  The camera's frame travels only at the rate the page's camera panel draws it (one state in
  every ``frame_every`` ticks carries it, as plain pixels; the others carry none): rendering and
  pickling 900 kB on every tick cost the loop's process more than the loop itself; and only while
  a browser has the page open (several leaders on one machine, none watched, each rendered
  frames nobody saw). The page keeps the newest frame (with its tick's CAMSHIFT windows) for the
  states between. ``lines``: the texts of the status lines other parts of the loop's process
  show on the page (the fleet bus's), read a few times a second and sent when one changed; ``skipped``: the ticks the loop
  has skipped so far (with the loop's target rate, given at start, the page's health banner judges
  them as in one process);
* page -> loop: ``("update", source, changes)``: every change the page's controls make, STOP
  included, applied by the loop's ParamsStore.update (the same validation as in one process;
  what it refuses is refused), ``("clients", n)`` when the number of browsers it serves
  changes, ``("alarm", t, text)`` when the page's health rules raise an alarm (the recorder
  writes it as an event), ``("failed", why, errno)`` when it cannot serve, and
  ``("ready", url, viewer_url, port)`` once it serves;
* the panels whose work runs on the loop's side (the Tuning panel: app.services.page_tuning) send
  and receive messages of their own kind, answered by the handler registered for it (``serve``);
  what the loop's side sends them is queued (``post``) and goes down the pipe before the next
  state, so no subscriber of the loop ever waits for the page.

Dead man's switch: if the page's process dies, the loop engages STOP at once and holds it (only
an operator's Release on a page lifts it), and a new page process is started on the same port
with the same tokens. If the loop's process dies, the page says so at once and then ends; the
followers stop on their link's watchdog (docs/follower-protocol.md).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from app.dashboard.camera_panel import REDRAW_S
from app.params import Params, ParamsStore
from app.refusals import refuse
from app.tick import LatestStatePublisher, TickState

log = logging.getLogger(__name__)

RESTART_PAUSE_S = 0.5  # between a dead page process and its successor (a crash loop stays cheap)
LINES_EVERY_S = 0.25  # how often the status lines' texts are read (the page's other panels redraw as often)
RETRY_S = 5.0  # a new page that could not serve (its port taken meanwhile) is tried again this often
ORPHAN_S = 3.0  # how long a page whose loop died keeps saying so before it ends
UNWATCHED_EVERY = 10  # with no browser on the page, one state in this many goes to it (3 a second at 30 Hz)


class PageProcess:
    """The loop's side: starts the page's process, feeds it ticks, applies its changes, restarts it."""

    def __init__(self, store: ParamsStore, host: str, port: int, token: str | None, viewer_token: str | None,
                 overlay: tuple[tuple[float, float], float, float] | None = None, obstacles: tuple[Any, ...] = (),
                 rate_hz: float = 30.0, recordings: Path | None = None) -> None:
        """``rate_hz``: the loop's; a frame goes to the page once every ``frame_every`` ticks (the
        camera panel's redraw period, REDRAW_S). ``recordings``: the folder the page's Recordings
        panel lists (its replays are served by the page's process: a replay commands no robot)."""
        self.recordings = recordings
        self._recording: tuple[str, str] | None = None  # (status text, file being written) to show
        self._recording_sent = False
        self.store = store
        self.rate_hz = rate_hz
        self.dropped: Callable[[], int] = lambda: 0  # the loop's skipped ticks so far (its health banner's)
        self.frame_every = max(1, math.floor(REDRAW_S * rate_hz + 0.5))
        self.frames_sent = 0  # states sent with the camera's frame
        self.clients = 0  # browsers the page serves now (it says when this changes)
        self.states_sent = 0
        self.handed = 0  # states handed to the sender (it skips one superseded before it went)
        self._worst_latency_ms = -math.inf  # the longest frame-to-command of the ticks not handed since the last
        self._frame_tick = -(10**9)  # the tick of the last state sent with its frame
        self.alarms: list[Callable[[float, str], None]] = []  # told of each alarm the page raises
        self._lines: list[Callable[[], str]] = []  # status lines shown on the page (add_line)
        self._outbox: deque[tuple[Any, ...]] = deque()  # messages for the page, sent before the next state
        self._handlers: dict[str, Callable[[tuple[Any, ...]], None]] = {}  # a panel's messages, by kind
        self.before_send: list[Callable[[], None]] = []  # called before each state goes (a panel's status)
        self.new_page: list[Callable[[], None]] = []  # called when a page process starts (its history)
        self.tuning: tuple[bool, bool] = (False, False)  # serve the Tuning panel; with vision sweeps
        self.calibration: tuple[Any, tuple[float, float], Any] | None = None  # a real camera's (detect, centre, area)
        self._lines_sent: tuple[str, ...] = ()
        self._lines_at = 0.0
        self.host = host
        self.port = port
        self.token = token  # the gate's, once it serves: kept across restarts (the operator's URL stays valid)
        self.viewer_token = viewer_token
        self.overlay = overlay
        self.obstacles = obstacles
        self.url = ""
        self.viewer_url = ""
        self.restarts = 0  # page processes started again after one died
        self.served = 0  # page processes that came up and served
        self._ctx = multiprocessing.get_context("spawn")
        self._closed = False
        self._conn: multiprocessing.connection.Connection | None = None
        self._proc: Any = None
        self._ready = threading.Event()
        self._failed: tuple[int | None, str] | None = None  # why the page could not serve (errno, text): no page again
        self._send_lock = threading.Lock()  # one writer at a time on the pipe (interleaved pickles corrupt it)
        self._sent_version = -1
        self._sender = LatestStatePublisher(self._send, name="page-sender")  # the newest state, never the loop's wait

    def serve(self, kind: str, handler: Callable[[tuple[Any, ...]], None]) -> None:
        """Messages of ``kind`` from the page go to ``handler`` (on the supervisor's thread)."""
        self._handlers[kind] = handler

    def post(self, msg: tuple[Any, ...]) -> None:
        """Queue a message for the page (any thread; it goes before the next state)."""
        self._outbox.append(msg)

    def start(self) -> None:
        """Start the page's process and wait until it serves."""
        self.launch()
        self.wait_ready()

    def launch(self) -> None:
        """Start the page's process and return at once (it takes a second or two to import and serve:
        the loop's side warms its kernels meanwhile); wait_ready() waits for it."""
        self._start_page()
        threading.Thread(target=self._supervise, name="page-supervisor", daemon=True).start()

    def wait_ready(self) -> None:
        """Wait until the page serves; OSError if it could not (its errno, as binding here would say)."""
        if not self._ready.wait(120.0):
            raise OSError("the page's process did not start")
        if self._failed:
            raise OSError(*self._failed) if self._failed[0] else OSError(self._failed[1])

    @property
    def pid(self) -> int:
        return int(self._proc.pid) if self._proc is not None else 0

    def _start_page(self) -> None:
        ours, theirs = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(target=page_main, name="omniformation-page", daemon=True,
                                 args=(theirs, self.host, self.port, self.token, self.viewer_token, self.store.get(),
                                       self.overlay, self.obstacles, self.recordings, self.rate_hz, self.tuning,
                                       self.calibration))
        proc.start()
        theirs.close()
        self._conn, self._proc = ours, proc
        self._sent_version = -1
        self._frame_tick = -(10**9)  # the new page gets a frame at once
        self._lines_sent = ()  # and the status lines
        self._recording_sent = False  # and the recording's name
        self._outbox.clear()  # what was queued for the page that died
        self.clients = 0  # nobody has the new page open yet
        for fn in self.new_page:
            fn()

    def add_line(self, text: Callable[[], str]) -> None:
        """A status line on the page, its text read from ``text`` a few times a second in this process."""
        self._lines.append(text)

    def show_recording(self, status: str, current: str) -> None:
        """The recording's state on the page's status line and the file its Recordings panel must
        not offer while it is written; sent before the next tick."""
        self._recording = (status, current)
        self._recording_sent = False

    def on_tick(self, state: TickState) -> None:
        """A loop subscriber: keep the newest state for the sender (never blocks the loop). With
        no browser on the page, one state in UNWATCHED_EVERY: its charts' history and health rules
        go on at 3 a second (at 30 Hz) and its process idles, as several unwatched leaders on one
        machine need (the page's process wakes for each state: a vision leader's page took about a
        third as much CPU at one in 10 as at one in 3). That state's frame-to-command is the
        longest of the ticks since the last one went, so the health rule's alarm for a tick longer
        than a period sees every tick. Every state again from the tick after a browser comes."""
        if self.clients == 0:
            worst = self._worst_latency_ms
            if math.isfinite(state.latency_ms) and not state.latency_ms <= worst:
                worst = state.latency_ms
            if state.tick % UNWATCHED_EVERY:
                self._worst_latency_ms = worst
                return
            if math.isfinite(worst) and not worst <= state.latency_ms:  # (a tick that observed nothing: NaN)
                state = dataclasses.replace(state, latency_ms=worst)
        self._worst_latency_ms = -math.inf
        self.handed += 1
        self._sender(state)

    def _send(self, state: TickState) -> bool:
        """One state (and the parameters, when they changed) down the pipe; False if the page is gone."""
        conn = self._conn
        params = self.store.get()
        changed = params if params.version != self._sent_version else None
        lines = None
        for fn in self.before_send:
            fn()
        now = time.monotonic()
        if self._lines and now - self._lines_at >= LINES_EVERY_S:
            self._lines_at = now
            texts = tuple(fn() for fn in self._lines)
            lines = texts if texts != self._lines_sent else None
        framed = False
        if state.frame is not None:  # rendered and sent only while someone has the page open
            framed = self.clients > 0 and (state.tick - self._frame_tick >= self.frame_every
                                           or state.tick < self._frame_tick)  # (a reset)
            pixels = np.ascontiguousarray(np.asarray(state.frame)) if framed else None  # a synthetic frame renders here
            state = dataclasses.replace(state, frame=pixels)
        try:
            assert conn is not None
            with self._send_lock:
                recording = self._recording
                if recording is not None and not self._recording_sent:
                    conn.send(("recording", *recording))
                    self._recording_sent = recording is self._recording
                while self._outbox:
                    conn.send(self._outbox.popleft())
                conn.send(("tick", state, changed, lines, self.dropped()))
            self._sent_version = params.version
            if lines is not None:
                self._lines_sent = lines
            self.states_sent += 1
            if framed:
                self._frame_tick = state.tick
                self.frames_sent += 1
            return True
        except (OSError, ValueError, AssertionError):
            time.sleep(0.05)  # the page is gone: the supervisor restarts it
            return False

    def _supervise(self) -> None:
        """Apply the page's changes; when it dies, STOP (held) and start a new one."""
        while not self._closed:
            conn = self._conn
            assert conn is not None
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                if self._closed or self._failed:
                    return
                self.store.update("loop", stop=True)  # the dead man's switch: no operator page, no motion
                print("omniformation: the page's process ended; STOP engaged and held until an operator"
                      " releases it on the new page", flush=True)
                self._proc.join(5.0)
                time.sleep(RESTART_PAUSE_S)
                if self._closed:
                    return
                self.restarts += 1
                self._start_page()
                continue
            if msg[0] == "update":
                _, source, changes = msg
                try:
                    self.store.update(str(source), **dict(changes))
                except (ValueError, TypeError) as exc:  # refused as the store refuses any bad change
                    refuse("page: change refused", str(source), str(exc), log)
            elif msg[0] == "clients" and len(msg) == 2:
                self.clients = max(0, int(msg[1]))
            elif msg[0] == "alarm" and len(msg) == 3:
                for fn in list(self.alarms):
                    fn(float(msg[1]), str(msg[2]))
            elif isinstance(msg[0], str) and msg[0] in self._handlers:
                self._handlers[msg[0]](msg)
            elif msg[0] == "failed":
                if not self._ready.is_set():  # the first page: `run` says why and ends
                    self._failed = (msg[2] if len(msg) > 2 and isinstance(msg[2], int) else None, str(msg[1]))
                    self._ready.set()
                    return
                log.warning("page: a new page cannot serve yet (%s); STOP stays engaged, trying again", msg[1])
                time.sleep(RETRY_S)
            elif msg[0] == "ready":
                _, self.url, self.viewer_url, self.port, self.token, self.viewer_token = msg
                self.served += 1
                self._ready.set()

    def close(self) -> None:
        self._closed = True
        self._sender.close()
        conn = self._conn
        if conn is not None:  # asked to end; sent aside: a hung page with the pipe full must not hold us here
            threading.Thread(target=self._say_close, args=(conn,), daemon=True).start()
        if self._proc is not None:
            self._proc.join(5.0)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(5.0)

    def _say_close(self, conn: multiprocessing.connection.Connection) -> None:
        with self._send_lock:
            try:
                conn.send(("close",))
            except (OSError, ValueError):
                pass


class ForwardingStore(ParamsStore):
    """The page's store: its controls' changes go to the loop (and show at once here); what the
    loop puts in force replaces them when it arrives.

    Every write of the store goes through :meth:`ParamsStore.change` (``update`` is a change that
    does not look at what is in force), so that is where the changes are sent: Pause, a change
    decided on what is in force ("paused = not paused"), once wrote only this copy and the loop
    never paused. What goes down the pipe is what the decision made of this copy (the parameters
    the loop last sent, which is what the operator sees: the button said "Pause", so the loop is
    told ``paused = True``), as an ``update`` the loop's store validates again."""

    def __init__(self, initial: Params, conn: multiprocessing.connection.Connection) -> None:
        super().__init__(initial)
        self._conn = conn
        self.send_lock = threading.Lock()  # one writer at a time on the pipe

    def change(self, source: str, decide: Callable[[Params], dict[str, Any]]) -> tuple[Params, tuple[Any, ...]]:
        decided: dict[str, Any] = {}

        def keep(current: Params) -> dict[str, Any]:
            changes = decide(current)
            decided.update(changes)
            return changes

        result = super().change(source, keep)  # refused here (ValueError): nothing goes to the loop
        if decided:
            with self.send_lock:
                try:
                    self._conn.send(("update", source, decided))
                except (OSError, ValueError):
                    pass  # the loop is gone: the page says so
        return result


def goal_check_for(obstacles: tuple[Any, ...]) -> Callable[[tuple[float, float]], str | None]:
    """Why a goal cannot be reached in a world with these boxes (None: it can): the loop's store and
    the page's (in its own process) check alike."""
    from core.config import LEADER_RADIUS_M
    from core.obstacles import as_array, surface_distance

    boxes = as_array(obstacles)

    def check(goal: tuple[float, float]) -> str | None:
        gap = float(surface_distance(np.array([goal]), boxes).min())
        if gap < LEADER_RADIUS_M:
            return f"is {max(gap, 0.0) * 100:.0f} cm from an obstacle's surface (the leader needs {LEADER_RADIUS_M * 100:.0f})"
        return None

    return check


def _tell_clients(server: Any, send: Callable[[tuple[Any, ...]], bool]) -> None:
    """Tell the loop how many browsers the page serves whenever that changes (with none, it
    sends no camera frame)."""
    watching: set[int] = set()
    lock = threading.Lock()

    def watched(client: Any, on: bool) -> None:
        with lock:
            (watching.add if on else watching.discard)(client.client_id)
            count = len(watching)
        send(("clients", count))

    server.on_client_connect(lambda client: watched(client, True))
    server.on_client_disconnect(lambda client: watched(client, False))


def page_main(conn: multiprocessing.connection.Connection, host: str, port: int, token: str | None,
              viewer_token: str | None, params: Params, overlay: tuple[tuple[float, float], float, float] | None,
              obstacles: tuple[Any, ...], recordings: Path | None = None, rate_hz: float = 0.0,
              tuning: tuple[bool, bool] = (False, False),
              calibration: tuple[Any, tuple[float, float], Any] | None = None) -> None:
    """The page's process: the gate, viser and the dashboard, drawing what the loop sends, the
    Recordings panel (replays served from here), the Tuning panel (its work on the loop's side) and,
    with a real camera (``calibration``: its detect settings, centre and working area), the
    Calibration panel on the full-size frames the loop sends."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the loop's process to handle: it closes this one
    # A session of its own, hence an autogroup of its own (sched(7)): the kernel shares CPU between
    # autogroups as equals, so the page's work (encoding for its browsers) no longer shares the
    # loop's. With a browser on the same 2 CPUs as an equal, the frame-to-command p99 went from a
    # median of 9.9 ms to 7.4 ms over eight runs each (`omniformation bench`, "an equal"). The page
    # still ends with the loop's process: it reads the pipe, which closes when that process dies.
    with contextlib.suppress(OSError):  # already a session's leader (started by hand): as it is
        os.setsid()
    from app.dashboard import Dashboard, LatestStatePublisher
    from app.dashboard.camera_panel import Overlay
    from app.dashboard.gate import new_token, quietly, serve_gated
    from app.dashboard.recordings_panel import RecordingsPanel
    from app.dashboard.tuning_panel import TuningPanel
    from app.services.page_tuning import PageBench
    from app.dashboard.widgets import on_page_thread
    from app.services.replay_process import ReplayProcess

    store = ForwardingStore(params, conn)
    if obstacles:  # a goal the loop would refuse is refused here too (Drive to goal then leaves the mode as it was)
        store.goal_check = goal_check_for(obstacles)
    try:
        server, gate = serve_gated(host, port, token, viewer_token)
    except OSError as exc:  # a port in use, an address this machine does not have: said once, by `run`
        conn.send(("failed", str(exc), exc.errno))  # the errno: `run` words it as in one process (app.files)
        return

    def send(msg: tuple[Any, ...]) -> bool:
        with store.send_lock:
            try:
                conn.send(msg)
                return True
            except (OSError, ValueError):
                return False  # the loop is gone: the page says so

    _tell_clients(server, send)
    bench = PageBench(send, tuning[1]) if tuning[0] else None
    dashboard = Dashboard(server, store, Overlay(*overlay) if overlay is not None else None, obstacles,
                          tuning=(lambda s: TuningPanel(s, store, bench)) if bench is not None else None)
    gate.filter.allow_viewer(dashboard.controls.stop_button)  # stopping is always safe
    dashboard.controls.who = gate.who  # STOP names who pressed it
    skipped = [0, -1]  # the loop's skipped ticks as the newest state said, and as the first did (a new page
    # after a restart judges only what is skipped while it serves)
    dashboard.controls.health.target_hz = rate_hz
    dashboard.controls.health.dropped = lambda: skipped[0] - max(skipped[1], 0)

    def replay(path: Path) -> ReplayProcess:
        """A replay with credentials of its own (as in one process: the live page's token never
        goes into a link), in a process of its own at the lowest priority (app.services.replay_process);
        a file that is no recording raises a ValueError."""
        return ReplayProcess(path, host, new_token() if gate.token else None, new_token())

    panel = RecordingsPanel(server, replay, recordings, role_of=gate.role_of)
    dashboard.controls.cause = lambda: panel.cause("by a process of its own at the lowest priority")
    dashboard.watched = lambda: gate.open_connections > 0  # nobody connected: nothing drawn, history kept
    publisher = LatestStatePublisher(dashboard.publish)

    def alarm(t: float, text: str) -> None:
        send(("alarm", t, text))  # the recorder writes it as an event (a gone loop: the page says so)

    dashboard.controls.health.listeners.append(alarm)
    with store.send_lock:
        conn.send(("ready", gate.url, gate.viewer_url, gate.port, gate.token, gate.viewer_token))
    loop_version = -1
    framed: TickState | None = None  # the newest state that carried the camera's frame
    newest = PageFrames()  # its pixels, full size, for the Calibration panel
    calibrating: Any = None  # the panel, made when the first frame tells the picture's size
    made: list[Any] = []
    shown: list[Any] = []  # the status lines' markdown, made when their first texts arrive
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):  # the loop's process is gone
                publisher.close()  # first: a tick still queued would draw its status over what follows
                dashboard.controls.status.content = ("**THE LOOP HAS ENDED: its process is gone. The followers stop"
                                                     " on their link's watchdog.**")
                time.sleep(ORPHAN_S)
                break
            if msg[0] == "close":
                break
            if msg[0] == "tuning" and bench is not None:
                bench.receive(msg)
                continue
            if msg[0] == "recording":
                _, dashboard.controls.recording, panel.current = msg
                panel.rescan()
                continue
            if msg[0] == "tick":
                _, state, changed, lines, skipped[0] = msg
                skipped[1] = skipped[0] if skipped[1] < 0 else skipped[1]
                if lines is not None:
                    on_page_thread(server, functools.partial(_show_lines, server, shown, lines))
                if changed is not None and changed.version != loop_version:
                    loop_version = changed.version
                    store.load(changed, "loop")  # what the loop put in force, shown on the controls
                if state.frame is not None:
                    framed = state
                    if calibration is not None:
                        newest.put(state.frame)
                        if calibrating is None and on_page_thread(server, functools.partial(
                                _calibrate, server, dashboard, newest, calibration, made)):
                            calibrating = made[0] if made else None
                elif framed is not None and framed.tick <= state.tick:  # the newest frame, with its own windows
                    state = dataclasses.replace(state, frame=framed.frame, windows=framed.windows)
                publisher(state)
    finally:
        publisher.close()
        panel.close()
        gate.close()
        quietly(server.stop)
    _end_now()


def _end_now() -> None:
    """End the page's process once it has closed what it serves: what it owns is closed above and it
    writes no file, so the interpreter's own teardown (modules, caches: about 0.4 s) is skipped, and
    Ctrl-C or a closing test does not wait for it."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(0)


def _show_lines(server: Any, shown: list[Any], texts: tuple[str, ...]) -> None:
    """The status lines' texts on the page (a markdown each, made the first time)."""
    while len(shown) < len(texts):
        shown.append(server.gui.add_markdown(""))
    for line, text in zip(shown, texts):
        if line.content != text:
            line.content = text


class PageFrames:
    """The page's camera, for its Calibration panel: the newest full-size frame the loop sent
    (app.contracts.FrameSource); capture, propose and save use it in the page's process."""

    name = "the loop's camera"
    state = "ok"

    def __init__(self) -> None:
        self._newest: tuple[np.ndarray | None, float, int] = (None, 0.0, 0)

    def put(self, frame: Any) -> None:
        self._newest = (np.asarray(frame), time.monotonic(), self._newest[2] + 1)

    def latest(self) -> tuple[np.ndarray | None, float, int]:
        return self._newest

    def wait_newer(self, count: int, timeout: float) -> int:
        return self._newest[2]

    def close(self) -> None:
        pass


def _calibrate(server: Any, dashboard: Any, frames: PageFrames, calibration: tuple[Any, tuple[float, float], Any],
               made: list[Any]) -> None:
    """The Calibration panel, once the camera's first frame is here (its sliders span the picture)."""
    from app.dashboard.calibration_panel import CalibrationPanel

    detect, centre, area = calibration
    panel = CalibrationPanel(server, frames, detect, Path("camera.toml"), centre=centre, area=area)
    dashboard.extra.append(panel.refresh)
    made.append(panel)
