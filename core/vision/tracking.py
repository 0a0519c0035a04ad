"""CAMSHIFT colour tracking of one follower's rectangle (paper §3.1–3.3), on a region of
interest around its window so the cost does not grow with the image size."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from core.camera.config import DetectSettings
from core.jit import kernel
from core.types import Image

HUE_BINS = 30  # 6 degrees per bin
_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.5)

# OpenCV's 8-bit BGR->HSV (hue 0..179) is integer arithmetic with 12-bit fixed-point
# reciprocals; these are its tables, so the kernel below gives its bytes exactly (the tests
# compare it with OpenCV on all 2^24 colours).
_HSV_SHIFT = 12
_I = np.arange(256, dtype=np.float64)
_SDIV = np.where(_I > 0, np.rint((255 << _HSV_SHIFT) / np.maximum(_I, 1.0)), 0.0).astype(np.int64)
_HDIV = np.where(_I > 0, np.rint((180 << _HSV_SHIFT) / (6.0 * np.maximum(_I, 1.0))), 0.0).astype(np.int64)
del _I


@kernel
def backproject_kernel(bgr: np.ndarray, area: np.ndarray, lut: np.ndarray, min_s: int, min_v: int,
                        sdiv: np.ndarray, hdiv: np.ndarray, out: np.ndarray) -> None:
    half = 1 << (_HSV_SHIFT - 1)
    for y in range(bgr.shape[0]):
        for x in range(bgr.shape[1]):
            b = np.int64(bgr[y, x, 0])
            g = np.int64(bgr[y, x, 1])
            r = np.int64(bgr[y, x, 2])
            v = max(b, g, r)
            diff = v - min(b, g, r)
            if v < min_v or (diff * sdiv[v] + half) >> _HSV_SHIFT < min_s:  # value, saturation floors
                out[y, x] = 0
                continue
            if v == r:
                h = g - b
            elif v == g:
                h = b - r + 2 * diff
            else:
                h = r - g + 4 * diff
            h = (h * hdiv[diff] + half) >> _HSV_SHIFT
            if h < 0:
                h += 180
            out[y, x] = lut[h] & area[y, x]


def hue_lookup(hist: np.ndarray) -> np.ndarray:
    """(256,) uint8: what ``cv2.calcBackProject`` gives a pixel of each hue byte under
    ``hist`` (asked of OpenCV itself, on a ramp of every hue byte)."""
    ramp = np.zeros((1, 256, 3), np.uint8)
    ramp[0, :, 0] = np.arange(256)
    return np.ascontiguousarray(cv2.calcBackProject([ramp], [0], hist, [0, 180], 1).reshape(256))


def back_projection(bgr: Image, lut: np.ndarray, area_mask: np.ndarray, detect: DetectSettings) -> np.ndarray:
    """The CAMSHIFT input of a BGR region in one pass: the hue histogram's back-projection
    (``lut`` from :func:`hue_lookup`) where saturation and value pass ``detect``'s floors,
    ANDed with the working-area mask. Byte for byte what cvtColor → calcBackProject →
    inRange → bitwise_and gives, without the four intermediate images.

    Both regions are handed to the kernel contiguous, whatever they were: a window cut from a
    camera's frame is a strided view, a rectangle the synthetic camera rendered alone is not, and
    numba compiles the kernel once for each layout it meets. The loop's warm-up (app.live.warmup)
    runs the synthetic camera, so a real rig's strided windows met an uncompiled kernel in a paced
    tick, which stalled while it compiled; copying a window costs microseconds."""
    a = np.ascontiguousarray(bgr)
    out = np.empty(a.shape[:2], np.uint8)
    backproject_kernel(a, np.ascontiguousarray(area_mask), lut, int(detect.min_saturation), int(detect.min_value),
                        _SDIV, _HDIV, out)
    return out


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
    lut: np.ndarray = field(init=False, repr=False)  # hue byte -> back-projection, from hist

    def __post_init__(self) -> None:
        self.lut = hue_lookup(self.hist)

    def keep_apart(self, other_hues_deg: tuple[float, ...]) -> None:
        """Count no hue byte nearer another follower's colour than this one's (the histogram
        is widened by a bin each side, which would reach a neighbour 15 deg away)."""
        lut = hue_lookup(self.hist)
        if other_hues_deg:
            deg = np.arange(256) * 2.0 % 360.0  # OpenCV hue bytes are degrees / 2 (180+: wrap)

            def dist(h: float) -> np.ndarray:
                d = np.abs(deg - h) % 360.0
                return np.minimum(d, 360.0 - d)

            own = dist(self.hue_deg)
            nearer_other = np.min(np.stack([dist(h) for h in other_hues_deg]), axis=0) < own
            lut[nearer_other] = 0
        self.lut = np.ascontiguousarray(lut)


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
    prob = back_projection(frame_bgr[y0:y1, x0:x1], track.lut, area_mask[y0:y1, x0:x1], detect)
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
