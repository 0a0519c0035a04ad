"""The viser dashboard: 3D scene, live plots, operator controls, status.

Built once; per tick it only assigns positions / orientations / visibility
inside ``server.atomic()``. Controls only write to the ParamsStore.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import viser

from core.obstacles import Obstacle

from app.dashboard.camera_panel import CameraPanel, Overlay
from app.dashboard.controls import Controls
from app.dashboard.plots import Plots
from app.dashboard.scene import Scene
from app.dashboard.tuning_panel import LyapunovMonitor, TuningPanel
from app.dashboard.widgets import on_page_thread
from app.tick import TickState
from app.params import ParamsStore


LIGHT_SCENE_S = 0.2  # light mode: the 3D view (and the camera) at most this often
LIGHT_PLOTS_S = 2.0  # and the charts


class Dashboard:
    """Wires the three parts to one viser server; ``publish`` is the loop's subscriber."""

    def __init__(self, server: viser.ViserServer, store: ParamsStore, overlay: Overlay | None = None,
                 obstacles: tuple[Obstacle, ...] = (), tuning: Callable[[viser.ViserServer], TuningPanel] | None = None,
                 ) -> None:
        """``tuning``: makes the live page's Tuning panel (step tests, sweeps); a replay has none."""
        self.server = server
        server.gui.configure_theme(control_width="large", dark_mode=False)
        self.controls = Controls(server, store)
        self.scene = Scene(server, store, self.controls, obstacles)
        self.camera = CameraPanel(server, overlay, order=self.controls.status.order + 0.5)  # under the status
        self.tuning = tuning(server) if tuning is not None else None
        self.monitor = LyapunovMonitor(server)
        self.plots = Plots(server)
        self.extra: list[Callable[[], None]] = []  # other panels' redraws (the calibration preview), ~4 a second
        self._extra_at = 0.0
        self._scene_at = 0.0

    def publish(self, state: TickState) -> bool:
        """Draw ``state``, on viser's own thread (widgets.on_page_thread); whether it was drawn."""
        return on_page_thread(self.server, lambda: self._draw(state))

    def _draw(self, state: TickState) -> None:
        now = time.monotonic()
        light = bool(self.controls.light.value)  # a slow browser asked for less (page.js turns it on)
        scene = not light or now - self._scene_at >= LIGHT_SCENE_S or self.controls.replay
        if scene:
            self._scene_at = now
        with self.server.atomic():
            if scene:
                self.scene.update(state)
            self.controls.update_status(state)
        if scene:
            self.camera.update(state)
        self.monitor.update(state)
        if self.tuning is not None:
            self.tuning.update(state)
        self.plots.update(state, LIGHT_PLOTS_S if light and not self.controls.replay else None)
        if self.extra and now - self._extra_at >= 0.25:
            self._extra_at = now
            for fn in self.extra:
                fn()


class LatestStatePublisher:
    """Publishes on its own thread, always the newest state; the loop only hands states over.

    The robots' loop must never wait for the page server: drawing the scene, encoding the
    camera JPEG and serialising plots for every connected browser happen here, and a state
    that is superseded before it could be drawn is skipped (the plots keep their time axis).
    """

    def __init__(self, publish: Callable[[TickState], bool | None]) -> None:
        """``publish`` returns False for a state it could not draw (counted as skipped)."""
        self._publish = publish
        self._cv = threading.Condition()
        self._state: TickState | None = None
        self._closed = False
        self.published = 0
        self.skipped = 0
        self._thread = threading.Thread(target=self._run, name="omniformation-dashboard", daemon=True)
        self._thread.start()

    def __call__(self, state: TickState) -> None:
        with self._cv:
            if self._state is not None:
                self.skipped += 1
            self._state = state
            self._cv.notify()

    def _run(self) -> None:
        while True:
            with self._cv:
                while self._state is None and not self._closed:
                    self._cv.wait()
                if self._closed:
                    return
                state, self._state = self._state, None
            assert state is not None  # the wait above ends with a state, or on close
            try:
                if self._publish(state) is False:
                    self.skipped += 1
                else:
                    self.published += 1
            except Exception:  # a broken view must not take the page down with it
                logging.getLogger(__name__).exception("dashboard publish failed")

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify()
        self._thread.join(5.0)
