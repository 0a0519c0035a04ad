"""CAMSHIFT colour tracking of one follower's rectangle (paper §3.1–3.3), on a region of
interest around its window so the cost does not grow with the image size."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.camera.config import DetectSettings
from core.types import Image

HUE_BINS = 30  # 6 degrees per bin
_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.5)


def hue_histogram(hsv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The follower's colour (§3.1): hue histogram of its rectangle's pixels, peak scaled to 255."""
    hist = cv2.calcHist([hsv], [0], mask, [HUE_BINS], [0, 180])
    # a rectangle's hue spreads a little with lighting and noise: widen by one bin each side
    hist = hist.ravel()
    wide = np.maximum(hist, np.maximum(np.roll(hist, 1), np.roll(hist, -1)) * 0.5)
    peak = float(wide.max())
    return (wide * (255.0 / peak) if peak > 0 else wide).astype(np.float32).reshape(-1, 1)


@dataclass
class Track:
    """One follower's tracker state. The window is (x, y, w, h) in full-image pixels."""

    hist: np.ndarray
    hue_deg: float
    window: tuple[int, int, int, int]
    area_px: float  # area of the rectangle when it was learned
    u: float = math.nan  # last centroid
    v: float = math.nan
    mass_px: float = 0.0  # back-projection mass in the last window (pixels' worth)
    misses: int = 0


def _roi(window: tuple[int, int, int, int], margin: int, width: int, height: int) -> tuple[int, int, int, int]:
    x, y, w, h = window
    x0 = max(0, x - margin)
    y0 = max(0, y - margin)
    x1 = min(width, x + w + margin)
    y1 = min(height, y + h + margin)
    return x0, y0, x1, y1


def camshift(frame_bgr: Image, track: Track, area_mask: np.ndarray, detect: DetectSettings,
             margin_px: int = 16) -> bool:
    """Move the track's window with CAMSHIFT on the hue back-projection; True if the colour was seen.

    Updates window, centroid (moments of the back-projection inside the new window) and mass.
    """
    hgt, wid = frame_bgr.shape[:2]
    x0, y0, x1, y1 = _roi(track.window, margin_px, wid, hgt)
    if x1 - x0 < 2 or y1 - y0 < 2:
        track.mass_px = 0.0
        return False
    hsv = cv2.cvtColor(frame_bgr[y0:y1, x0:x1], cv2.COLOR_BGR2HSV)
    prob = cv2.calcBackProject([hsv], [0], track.hist, [0, 180], 1)
    sat = cv2.inRange(hsv, (0, detect.min_saturation, detect.min_value), (180, 255, 255))
    cv2.bitwise_and(prob, sat, dst=prob)
    cv2.bitwise_and(prob, area_mask[y0:y1, x0:x1], dst=prob)
    x, y, w, h = track.window
    local = (max(0, x - x0), max(0, y - y0), max(1, min(w, x1 - x0)), max(1, min(h, y1 - y0)))
    _, win = cv2.CamShift(prob, local, _CRITERIA)
    wx, wy, ww, wh = (int(c) for c in win)
    if ww <= 0 or wh <= 0:
        track.mass_px = 0.0
        return False
    sub = prob[wy:wy + wh, wx:wx + ww]
    m = cv2.moments(sub)
    if m["m00"] <= 0:
        track.mass_px = 0.0
        return False
    track.mass_px = m["m00"] / 255.0
    track.u = x0 + wx + m["m10"] / m["m00"]
    track.v = y0 + wy + m["m01"] / m["m00"]
    # keep the window a little larger than the blob so it can follow motion between frames
    pad = 2
    track.window = (x0 + wx - pad, y0 + wy - pad, ww + 2 * pad, wh + 2 * pad)
    return True
