"""The camera panel: the leader's current omnidirectional frame, downscaled, about 10 Hz,
with the working area, each follower's CAMSHIFT window, id and slot, and the pipeline's phase."""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
import viser

from core.camera.render.looks import follower_bgr
from app.tick import TickState

REDRAW_S = 0.1
SCALE = 0.5  # 640x480 -> 320x240

PHASE_TEXT = {"find": "start-up: finding the team by its marker hues", "base": "start-up: base background (everyone still)", "probe": "start-up: probing F{i}",
              "heading": "start-up: first headings (all drive forward)", "tracking": "tracking"}


@dataclass(frozen=True)
class Overlay:
    """Where the working area is in the image (paper fig. 8)."""

    center: tuple[float, float]
    inner_px: float
    outer_px: float


class CameraPanel:
    def __init__(self, server: viser.ViserServer, overlay: Overlay | None, order: float | None = None) -> None:
        self.overlay = overlay
        self._last = 0.0
        with server.gui.add_folder("Camera", order=order):
            self.image = server.gui.add_image(np.zeros((240, 320, 3), np.uint8), label="leader's camera",
                                              format="jpeg", jpeg_quality=75)
        self.frames_shown = 0

    def update(self, s: TickState) -> None:
        if s.frame is None:
            return
        now = time.monotonic()
        if now - self._last < REDRAW_S:
            return
        self._last = now
        self.image.image = self.annotate(s)[..., ::-1]  # viser wants RGB
        self.frames_shown += 1

    def annotate(self, s: TickState) -> np.ndarray:
        """The downscaled frame with the overlays drawn on it (BGR)."""
        assert s.frame is not None
        img = cv2.resize(np.asarray(s.frame), None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_AREA)
        if self.overlay is not None:
            c = (int(round(self.overlay.center[0] * SCALE)), int(round(self.overlay.center[1] * SCALE)))
            for r in (self.overlay.inner_px, self.overlay.outer_px):
                cv2.circle(img, c, int(round(r * SCALE)), (230, 180, 90), 1, cv2.LINE_AA)
        if s.windows is not None:
            for i in range(s.n):
                x, y, w, h = (int(round(v * SCALE)) for v in s.windows[i])
                if w <= 0 or h <= 0:
                    continue
                colour = follower_bgr(i)
                seen = bool(s.tracked[i])
                cv2.rectangle(img, (x, y), (x + w, y + h), colour if seen else (60, 60, 230), 1, cv2.LINE_AA)
                label = f"F{i + 1}" + (f">S{int(s.assignment[i]) + 1}" if s.phase == "tracking" else "")
                if not seen:
                    label += " lost"
                cv2.putText(img, label, (x, max(8, y - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (255, 255, 255), 2, cv2.LINE_AA)
                cv2.putText(img, label, (x, max(8, y - 3)), cv2.FONT_HERSHEY_SIMPLEX, 0.33, colour, 1, cv2.LINE_AA)
        text = PHASE_TEXT.get(s.phase, s.phase).format(i=s.probing + 1)
        cv2.putText(img, text, (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
        return img
