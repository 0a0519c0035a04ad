"""Saturated colour blobs (the followers' rectangles) in a frame, inside the working area.

Used by ``omniformation locate``, by the synthetic calibration and by the pipeline when it
searches for a lost follower by colour. Pieces of one colour lying close together are one
rectangle (paper fig. 10: a rectangle split by a reflection or by the image's distortion).

Two followers' markers are never joined: pieces merge only when their hues are within
``merge_hue_deg`` (a rectangle's pieces differ by a degree or two), which must stay under
``MIN_HUE_SEPARATION_DEG``, and never when each lies nearest a different one of the team's
known hues. Markers closer in hue than ``MIN_HUE_SEPARATION_DEG`` are refused by the config
(core.camera.config): one standing behind the other would blend into one blob and a robot
would silently disappear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.camera.config import MIN_HUE_SEPARATION_DEG, DetectSettings, hue_distance_deg, too_close_hues


@dataclass(frozen=True)
class Blob:
    hue_deg: float  # circular mean hue, degrees in [0, 360)
    u: float  # centroid (pixels)
    v: float
    area_px: int
    bbox: tuple[int, int, int, int]  # x, y, w, h


def nearest_hue(hue_deg: float, hues_deg: tuple[float, ...] | list[float]) -> int:
    """Index of the hue in ``hues_deg`` nearest ``hue_deg`` (-1 for none)."""
    if not hues_deg:
        return -1
    return min(range(len(hues_deg)), key=lambda k: hue_distance_deg(hue_deg, hues_deg[k]))


__all__ = ["MIN_HUE_SEPARATION_DEG", "Blob", "find_blobs", "hue_distance_deg", "merge_blobs", "nearest_hue",
           "too_close_hues"]


def saturated_mask(hsv: np.ndarray, area_mask: np.ndarray | None, detect: DetectSettings) -> np.ndarray:
    """255 where a pixel is saturated and bright enough (and inside the area mask)."""
    m = cv2.inRange(hsv, (0, detect.min_saturation, detect.min_value), (180, 255, 255))
    if area_mask is not None:
        m = cv2.bitwise_and(m, area_mask)
    return m


def circular_mean_hue_deg(hue_opencv: np.ndarray) -> float:
    """Mean of OpenCV hues (0..179, i.e. degrees / 2) on the circle, in degrees."""
    ang = hue_opencv.astype(np.float64) * (math.pi / 90.0)
    return math.degrees(math.atan2(float(np.sin(ang).mean()), float(np.cos(ang).mean()))) % 360.0


def find_blobs(bgr: np.ndarray, area_mask: np.ndarray | None, detect: DetectSettings,
               hsv: np.ndarray | None = None, known_hues: tuple[float, ...] = ()) -> list[Blob]:
    """Every saturated blob of at least ``min_area_px`` pixels, same-hue neighbours merged
    (never two nearest different ``known_hues``)."""
    if hsv is None:
        hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    sat = saturated_mask(hsv, area_mask, detect)
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(sat, connectivity=8)
    pieces: list[Blob] = []
    for k in range(1, count):
        x, y, w, h, area = (int(s) for s in stats[k])
        if area < 2:
            continue
        sub = labels[y:y + h, x:x + w] == k
        hue = circular_mean_hue_deg(hsv[y:y + h, x:x + w, 0][sub])
        pieces.append(Blob(hue, float(centroids[k, 0]), float(centroids[k, 1]), area, (x, y, w, h)))
    merged = merge_blobs(pieces, detect, known_hues)
    return [b for b in merged if b.area_px >= detect.min_area_px]


def _gap(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> float:
    dx = max(0, max(a[0], b[0]) - min(a[0] + a[2], b[0] + b[2]))
    dy = max(0, max(a[1], b[1]) - min(a[1] + a[3], b[1] + b[3]))
    return math.hypot(dx, dy)


def merge_blobs(pieces: list[Blob], detect: DetectSettings, known_hues: tuple[float, ...] = ()) -> list[Blob]:
    """Join same-hue pieces whose boxes lie within ``merge_distance_px`` (area-weighted);
    two pieces nearest different ``known_hues`` (two followers' markers) are never joined."""
    blobs = sorted(pieces, key=lambda b: -b.area_px)
    changed = True
    while changed:
        changed = False
        out: list[Blob] = []
        for b in blobs:
            for i, a in enumerate(out):
                if hue_distance_deg(a.hue_deg, b.hue_deg) <= detect.merge_hue_deg and _gap(a.bbox, b.bbox) <= detect.merge_distance_px \
                        and nearest_hue(a.hue_deg, known_hues) == nearest_hue(b.hue_deg, known_hues):
                    area = a.area_px + b.area_px
                    x0, y0 = min(a.bbox[0], b.bbox[0]), min(a.bbox[1], b.bbox[1])
                    x1 = max(a.bbox[0] + a.bbox[2], b.bbox[0] + b.bbox[2])
                    y1 = max(a.bbox[1] + a.bbox[3], b.bbox[1] + b.bbox[3])
                    wa, wb = a.area_px / area, b.area_px / area
                    hue = math.degrees(math.atan2(
                        wa * math.sin(math.radians(a.hue_deg)) + wb * math.sin(math.radians(b.hue_deg)),
                        wa * math.cos(math.radians(a.hue_deg)) + wb * math.cos(math.radians(b.hue_deg)))) % 360.0
                    out[i] = Blob(hue, wa * a.u + wb * b.u, wa * a.v + wb * b.v, area, (x0, y0, x1 - x0, y1 - y0))
                    changed = True
                    break
            else:
                out.append(b)
        blobs = out
    return blobs
