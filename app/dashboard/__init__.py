"""The viser dashboard: 3D scene, live plots, operator controls, status.

Built once; per tick it only assigns positions / orientations / visibility
inside ``server.atomic()``. Controls only write to the ParamsStore.
"""

from __future__ import annotations

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
from app.tick import LatestStatePublisher, TickState
from app.params import ParamsStore


__all__ = ["Dashboard", "LatestStatePublisher"]  # the publisher lives beside TickState (app.tick)
LIGHT_SCENE_S = 1.0  # light mode: the 3D view (and the camera) at most this often (docs/page-access.md)
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
        self._shadows_off = False
        # None: always drawn. Else drawn only while it says someone watches; otherwise only what
        # the page must not miss is kept (_keep). The page in its own process sets it (app.services.page_process).
        self.watched: Callable[[], bool] | None = None

    def publish(self, state: TickState) -> bool:
        """Draw ``state``, on viser's own thread (widgets.on_page_thread); whether it was drawn."""
        return on_page_thread(self.server, lambda: self._draw(state))

    def _draw(self, state: TickState) -> None:
        if self.watched is not None and not self.watched():
            self._keep(state)
            return
        now = time.monotonic()
        light = bool(self.controls.light.value)  # a slow browser asked for less (page.js turns it on)
        if light != self._shadows_off:  # light mode: no shadows (a software frame took 13 times as long with them)
            self._shadows_off = light
            self.server.scene.configure_default_lights(enabled=True, cast_shadow=not light)
        scene = not light or now - self._scene_at >= LIGHT_SCENE_S or self.controls.replay or self.scene.asked
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

    def _keep(self, state: TickState) -> None:
        """A tick nobody watches: what the page must not miss (its health rules, which raise the
        alarms the recording keeps; the charts' and the monitor's history; the Tuning panel's
        team), none of the drawing. A page that connects is drawn whole by the next tick: every
        part's redraw is due by then. Measured: an arena leader's page, no browser, took 3.1 % of
        a CPU drawing for nobody."""
        self.controls.judge(state)
        self.plots.add(state)
        self.monitor.add(state)
        if self.tuning is not None:
            self.tuning.update(state)
