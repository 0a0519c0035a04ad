"""Calibrating from a live picture: the mirror's circle found in the image, where to put the
next marker, and one marker found (or refused, saying why) in a capture.

The page (app/dashboard/calibration_panel.py) and ``omniformation calibrate --page`` use
these; the fit itself is core.camera.gamma's and its quality core.camera.quality's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.camera.config import DetectSettings, WorkingArea
from core.vision.blobs import Blob, find_blobs

GUIDE_BEARINGS = 4  # around the leader, evenly (at most 100 deg apart: no coverage warning)
GUIDE_DISTANCES_M = (0.5, 0.75, 1.0, 1.25, 1.5, 1.75)  # 4 x 6 = 24 captures


def guide_targets(bearings: int = GUIDE_BEARINGS,
                  distances: tuple[float, ...] = GUIDE_DISTANCES_M) -> list[tuple[float, float]]:
    """(bearing deg, distance m) in the order the page asks for them: each distance at every
    bearing before the next distance, so the coverage grows evenly all round."""
    step = 360.0 / bearings
    return [(round(step * k, 6), d) for d in distances for k in range(bearings)]


def next_target(targets: list[tuple[float, float]], captured: list[tuple[float, float]]) -> tuple[float, float] | None:
    """The first target no capture has taken yet (a capture counts for the target at its
    bearing and distance within 5 deg and 5 cm)."""
    for b, d in targets:
        if not any(abs((b - cb + 180.0) % 360.0 - 180.0) < 5.0 and abs(d - cd) < 0.05 for cb, cd in captured):
            return b, d
    return None


@dataclass(frozen=True)
class Circle:
    cx: float
    cy: float
    radius: float


def fit_mirror_circle(bgr: np.ndarray, dark: int = 12) -> Circle | None:
    """The mirror's image: the lit disc inside the dark surround of an omnidirectional picture.
    Least squares circle through the disc's outline (the largest lit region's contour)."""
    grey = cv2.cvtColor(np.asarray(bgr), cv2.COLOR_BGR2GRAY) if np.asarray(bgr).ndim == 3 else np.asarray(bgr)
    lit = np.asarray((grey > dark).astype(np.uint8) * 255, dtype=np.uint8)
    closed = cv2.morphologyEx(lit, cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    contours, _ = cv2.findContours(closed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return None
    outline = max(contours, key=cv2.contourArea).reshape(-1, 2).astype(np.float64)
    h, w = grey.shape[:2]
    # the image's own border is not the mirror's: keep the outline points inside it
    inside = (outline[:, 0] > 1) & (outline[:, 0] < w - 2) & (outline[:, 1] > 1) & (outline[:, 1] < h - 2)
    pts = outline[inside]
    if len(pts) < 20:
        return None
    x, y = pts[:, 0], pts[:, 1]
    a = np.column_stack([x, y, np.ones_like(x)])
    sol, *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    cx, cy = sol[0] / 2, sol[1] / 2
    r2 = sol[2] + cx * cx + cy * cy
    if not r2 > 0:
        return None
    return Circle(float(cx), float(cy), float(math.sqrt(r2)))


def find_marker(bgr: np.ndarray, centre: tuple[float, float], area: WorkingArea,
                detect: DetectSettings) -> Blob | str:
    """The one marker in a capture, or why it cannot be taken (no blob; more than one; one
    outside the working area)."""
    img = np.asarray(bgr)
    h, w = img.shape[:2]
    blobs = find_blobs(img, None, detect)
    if not blobs:
        return "no marker in the picture: put one coloured marker where the guide says"
    radius = np.array([math.hypot(b.u - centre[0], b.v - centre[1]) for b in blobs])
    inside = (radius >= area.inner_px) & (radius <= area.outer_px)
    if not inside.any():
        b = blobs[int(np.argmax([bl.area_px for bl in blobs]))]
        r = math.hypot(b.u - centre[0], b.v - centre[1])
        return (f"the marker at pixel ({b.u:.0f}, {b.v:.0f}) is {r:.0f} px from the centre, outside the working"
                f" area ({area.inner_px:g}..{area.outer_px:g} px): move it nearer, or widen the area")
    if int(inside.sum()) > 1:
        where = ", ".join(f"({b.u:.0f}, {b.v:.0f})" for b, ok in zip(blobs, inside) if ok)
        return f"{int(inside.sum())} markers in the working area at {where}: leave only one"
    return blobs[int(np.flatnonzero(inside)[0])]

