"""`omniformation replay FILE`: a recording in the same dashboard, with a timeline.

The same Dashboard object as a live run is fed recorded ticks instead of live ones. A
"Replay" panel has the timeline slider, play / pause, speed 0.25x-8x, step, and jumps to
the previous / next event. Controls that would command robots are disabled and say why.
"""

from __future__ import annotations

import bisect
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np
from typing import TYPE_CHECKING, Any

import viser

from app.dashboard import Dashboard
from app.dashboard.gate import quietly, serve_gated
from app.dashboard.widgets import as_text
from app.dashboard.widgets import on_page_thread
from app.tick import TickState
from app.params import ParamsStore
from app.recording.reader import Recording, params_from_payload, params_from_recording, params_index
from app.recording.schema import scenario_obstacles, tick_from_payload

if TYPE_CHECKING:
    from app.dashboard.camera_panel import Overlay

SPEEDS = ("0.25", "0.5", "1", "2", "4", "8")
PLAYBACK_HZ = 30.0
MAX_MARKS = 200  # events marked on the timeline (a session with more keeps them in the list)
MAX_LISTED = 2000  # events in the "Go to event" list


class ReplayService:
    def __init__(self, rec: Recording, host: str = "127.0.0.1", port: int = 8080, token: str | None = None,
                 viewer_token: str | None = None) -> None:
        """``token``, ``viewer_token``: this replay's own (app.dashboard.gate); a replay opened from the
        live page gets new ones, never the live page's (docs/page-access.md)."""
        self.rec = rec
        self.t = rec.t
        self.frame_t = rec.frame_t
        self.event_t = sorted(float(e["t"]) for e in rec.events)
        self.server, self.gate = serve_gated(host, port, token, viewer_token)
        self.gate.page_kind = "replay"  # the page says so, and its bar has no STOP
        self.store = ParamsStore(params_from_recording(rec))
        self._param_t = [at for at, _ in rec.params]  # when each recorded parameter set came in force
        self._params_shown = 0  # which of them the page shows
        self.dashboard = Dashboard(self.server, self.store, overlay=_overlay(rec), obstacles=scenario_obstacles(rec.metadata))
        self.dashboard.controls.set_replay(rec.path.name)
        gui = self.server.gui
        self.playing = False
        self.speed = 1.0
        self.index = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.published = 0
        self.unreadable = 0  # ticks that could not be shown (a damaged file)
        t0, t1 = float(self.t[0]), float(self.t[-1])
        with gui.add_folder("Replay", order=self.dashboard.controls.status.order + 0.25):
            marks = tuple(round(min(max(t, t0), t1), 3) for t in self.event_t[:MAX_MARKS])  # the events, on it
            self.timeline = gui.add_slider("Time (s)", min=round(t0, 3), max=round(max(t1, t0 + 1e-3), 3),
                                           step=1.0 / PLAYBACK_HZ, initial_value=round(t0, 3), marks=marks or None)
            self.play_button = gui.add_button("Play replay")
            self.speed_menu = gui.add_dropdown("Speed", options=SPEEDS, initial_value="1")
            self.step_button = gui.add_button("Step")
            self.prev_event = gui.add_button("Previous event")
            self.next_event = gui.add_button("Next event")
            self.event_text = gui.add_markdown(self._events_summary())
            self._event_labels = [f"{float(e['t']):.1f} s · {e.get('kind', '?')}: {str(e.get('detail', ''))[:80]}"
                                  for e in sorted(rec.events, key=lambda e: float(e["t"]))][:MAX_LISTED]
            self.event_list = gui.add_dropdown("Go to event", options=("-", *self._event_labels), initial_value="-",
                                               disabled=not self._event_labels,
                                               hint="every event the session recorded, in time order")
        if rec.loss_note():
            with gui.add_folder("Recording"):
                gui.add_markdown(f"**{as_text(rec.loss_note())}**")
        self._wire()
        self._thread: threading.Thread | None = None
        self.listeners: list[Callable[[TickState], None]] = []  # each tick shown, also to these (Foxglove live)

    def _events_summary(self) -> str:
        if not self.rec.events:
            return "no events recorded"
        return f"{len(self.rec.events)} events, e.g. " + "; ".join(
            f"{e['t']:.1f} s {e['detail']}" for e in self.rec.events[:3])

    @property
    def url(self) -> str:
        return self.gate.url

    @property
    def viewer_url(self) -> str:
        return self.gate.viewer_url

    # -- controls -------------------------------------------------------------------------
    def _wire(self) -> None:
        @self.play_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            with self._lock:
                if not self.playing and self.index >= len(self.t) - 1:
                    self.seek(0)
                self.playing = not self.playing
            self.play_button.label = "Pause replay" if self.playing else "Play replay"

        @self.speed_menu.on_update
        def _(event: viser.GuiEvent[Any]) -> None:
            self.speed = float(self.speed_menu.value)

        @self.step_button.on_click
        def _(event: viser.GuiEvent[Any]) -> None:
            with self._lock:
                self.playing = False
                self.seek(min(self.index + 1, len(self.t) - 1))
            self.play_button.label = "Play replay"

        @self.timeline.on_update
        def _(event: viser.GuiEvent[Any]) -> None:
            if event.client_id is None:  # our own update while playing
                return
            with self._lock:
                self.seek(self._index_at(float(self.timeline.value)), move_timeline=False)

        @self.event_list.on_update
        def _(event: viser.GuiEvent[Any]) -> None:
            if event.client_id is None or self.event_list.value == "-":
                return
            k = self._event_labels.index(str(self.event_list.value))
            self.go_to_event(k)

        @self.next_event.on_click
        def _(_: viser.GuiEvent[Any]) -> None:
            self.jump_to_event(+1)

        @self.prev_event.on_click
        def _(_: viser.GuiEvent[Any]) -> None:
            self.jump_to_event(-1)

    def jump_to_event(self, direction: int) -> float | None:
        """To the next (+1) or previous (-1) event's time: the first tick at or after it, so the
        next search starts past it (an event between two ticks once sent the seek just before it,
        and Next found the same event again). The event's time, or None when there is none."""
        with self._lock:
            now = float(self.t[self.index])
            if direction > 0:
                k = bisect.bisect_right(self.event_t, now + 1e-6)
                target = self.event_t[k] if k < len(self.event_t) else None
            else:
                k = bisect.bisect_left(self.event_t, now - 1e-6) - 1
                while k >= 0 and self._index_at_or_after(self.event_t[k]) >= self.index:
                    k -= 1  # an event this tick already shows (at or just before it) is not a step back
                target = self.event_t[k] if k >= 0 else None
            if target is not None:
                self.seek(self._index_at_or_after(target))
            return target

    def go_to_event(self, k: int) -> float:
        """To the k-th event in time order (the event list's row k): the first tick at or after it."""
        target = self.event_t[k]
        with self._lock:
            self.playing = False
            self.seek(self._index_at_or_after(target))
        self.play_button.label = "Play replay"
        return target

    def _index_at_or_after(self, t: float) -> int:
        return int(np.clip(np.searchsorted(self.t, t - 1e-6, side="left"), 0, len(self.t) - 1))

    def _index_at(self, t: float) -> int:
        return int(np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 1))

    # -- showing a tick -------------------------------------------------------------------
    def state_at(self, k: int, with_frame: bool = True) -> TickState:
        frame = None
        if with_frame and len(self.frame_t):
            j = bisect.bisect_right(self.frame_t, float(self.t[k]) + 1e-9) - 1
            if j >= 0:
                frame = cv2.imdecode(np.frombuffer(self.rec.frames[j][1], np.uint8), cv2.IMREAD_COLOR)
        return tick_from_payload(self.rec.ticks[k], frame)

    def seek(self, k: int, move_timeline: bool = True) -> None:
        """Show tick k; the plots get the 60 s before it again. ``index`` changes only once
        the state of tick k is published. ``move_timeline``: False when a viewer set the time
        themselves: the slider keeps what they gave (tick k is the last at or before it), and no
        echo arrives after the drawing to overwrite the next time they are typing."""
        plots = self.dashboard.plots
        plots.reset()
        t_now = float(self.t[k])
        start = self._index_at(t_now - 60.0)
        for j in range(start, k):
            try:
                plots.add(self.state_at(j, with_frame=False))
            except (KeyError, TypeError, ValueError, IndexError, AttributeError):
                self.unreadable += 1
        self._publish(k, move_timeline)
        self.index = k

    def _publish(self, k: int, move_timeline: bool = True) -> None:
        try:
            state = self.state_at(k)
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:  # a tick the file spoiled
            self.unreadable += 1
            self.event_text.content = f"**tick {k} could not be shown** ({type(exc).__name__}); playback goes on"
            return
        j = params_index(self._param_t, float(self.t[k]))
        for fn in self.listeners:
            fn(state)

        def draw() -> None:
            if j != self._params_shown and self.rec.params:  # the settings in force at this moment, not at the start
                self._params_shown = j
                self.store.load(params_from_payload(self.rec.params[j][1]), "replay")
            self.dashboard.publish(state)
            if move_timeline:
                self.timeline.value = round(float(self.t[k]), 3)  # type: ignore[misc]  # viser's stubs: read-only on the base handle

        if on_page_thread(self.dashboard.server, draw):
            self.published += 1

    def run(self) -> None:
        self.seek(0)
        period = 1.0 / PLAYBACK_HZ
        clock = float(self.t[0])
        while not self._stop.is_set():
            t_start = time.monotonic()
            with self._lock:
                if self.playing:
                    clock = max(clock, float(self.t[self.index])) + period * self.speed
                    k = self._index_at(clock)
                    if k >= len(self.t) - 1:
                        k = len(self.t) - 1
                        self.playing = False
                        self.play_button.label = "Play replay"
                    if k != self.index:
                        self._publish(k)
                        self.index = k
                else:
                    clock = float(self.t[self.index])
            self._stop.wait(max(0.0, period - (time.monotonic() - t_start)))

    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="omniformation-replay", daemon=True)
        self._thread.start()

    def wait(self) -> None:
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(0.2)

    def stop(self) -> None:
        """Ask the playback thread to end (signal handlers call this)."""
        self._stop.set()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.gate.close()
        quietly(self.server.stop)


def _overlay(rec: Recording) -> "Overlay | None":
    """The working-area overlay recorded with the session, if any."""
    from app.dashboard.camera_panel import Overlay

    try:
        cx, cy, inner, outer = (float(v) for v in rec.metadata.get("working_area", "").split(","))
    except ValueError:
        return None
    return Overlay((cx, cy), inner, outer)
