"""The viser dashboard: 3D scene, live plots, operator controls, status.

Built once; per tick it only assigns positions / orientations / visibility
inside ``server.atomic()``. Controls only write to the ParamsStore.
"""

from __future__ import annotations

import viser

from app.dashboard.camera_panel import CameraPanel, Overlay
from app.dashboard.controls import Controls
from app.dashboard.plots import Plots
from app.dashboard.scene import Scene
from app.loop import TickState
from app.params import ParamsStore


class Dashboard:
    """Wires the three parts to one viser server; ``publish`` is the loop's subscriber."""

    def __init__(self, server: viser.ViserServer, store: ParamsStore, overlay: Overlay | None = None) -> None:
        self.server = server
        server.gui.configure_theme(control_width="large", dark_mode=False)
        self.controls = Controls(server, store)
        self.scene = Scene(server, store, self.controls)
        self.camera = CameraPanel(server, overlay, order=self.controls.status.order + 0.5)  # under the status
        self.plots = Plots(server)

    def publish(self, state: TickState) -> None:
        with self.server.atomic():
            self.scene.update(state)
            self.controls.update_status(state)
        self.camera.update(state)
        self.plots.update(state)
