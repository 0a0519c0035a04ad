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
WORKING_RING_M = (0.3, 1.5)  # where followers drive around the leader (the page draws these two circles)
# From the ring's inner edge (followers drive there; Γ extrapolated inwards from 0.5 m was off by
# 6-12 cm p95 at 0.35-0.5 m on the catadioptric model, 1.0-1.6 cm with this plan), denser where
# the mirror's picture changes fastest, to a little beyond its outer edge: 4 x 8 = 32 captures.
GUIDE_DISTANCES_M = (WORKING_RING_M[0], 0.4, 0.5, 0.75, 1.0, 1.25, 1.5, 1.75)


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


RIM_MIN_SUPPORT = 0.7  # share of the rim's visible arc that must show a radial edge
RIM_MIN_VISIBLE = 0.4  # share of the circle that must lie inside the picture
RIM_TRIES = 120  # RANSAC draws per refinement


def _radial_edges(gx: np.ndarray, gy: np.ndarray, c: Circle, search: int,
                  samples: int = 1440) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Along ``samples`` rays from the circle's centre, within ``search`` px of its radius: the
    strongest radial edge (x, y, its strength) and whether the ray's point is inside the picture."""
    h, w = gx.shape
    th = np.linspace(0.0, 2.0 * np.pi, samples, endpoint=False)
    ux, uy = np.cos(th), np.sin(th)
    ds = np.arange(-search, search + 1, dtype=np.float64)[:, None]
    x, y = c.cx + (c.radius + ds) * ux, c.cy + (c.radius + ds) * uy
    inside = (x >= 2) & (x < w - 3) & (y >= 2) & (y < h - 3)
    xi = np.clip(np.rint(x).astype(np.intp), 0, w - 1)
    yi = np.clip(np.rint(y).astype(np.intp), 0, h - 1)
    g = np.abs(gx[yi, xi] * ux + gy[yi, xi] * uy) * inside
    k = g.argmax(axis=0)
    cols = np.arange(samples)
    return x[k, cols], y[k, cols], g[k, cols], inside[search, :]  # row `search` is the circle itself


def _circle_through(xs: np.ndarray, ys: np.ndarray) -> Circle | None:
    """Least squares (algebraic) circle through points."""
    a = np.column_stack([xs, ys, np.ones_like(xs)])
    sol, *_ = np.linalg.lstsq(a, xs * xs + ys * ys, rcond=None)
    cx, cy = sol[0] / 2, sol[1] / 2
    r2 = sol[2] + cx * cx + cy * cy
    return Circle(float(cx), float(cy), float(math.sqrt(r2))) if r2 > 0 else None


def _refine(gx: np.ndarray, gy: np.ndarray, c: Circle, strong: float, rng: np.random.Generator) -> Circle | None:
    """The circle the edges near ``c`` lie on: edge points along its rays, RANSAC for the circle
    most of them fit (within 1.5 px), least squares on those; three times, each nearer."""
    for search in (12, 6, 3):
        x, y, g, _ = _radial_edges(gx, gy, c, search)
        keep = g > strong
        xs, ys = x[keep], y[keep]
        if len(xs) < 30:
            return None
        pick = rng.integers(0, len(xs), (RIM_TRIES, 3))
        x1, y1, x2, y2, x3, y3 = xs[pick[:, 0]], ys[pick[:, 0]], xs[pick[:, 1]], ys[pick[:, 1]], xs[pick[:, 2]], ys[pick[:, 2]]
        d = 2.0 * (x1 * (y2 - y3) + x2 * (y3 - y1) + x3 * (y1 - y2))
        ok = np.abs(d) > 1e-6
        d = np.where(ok, d, 1.0)
        s1, s2, s3 = x1 * x1 + y1 * y1, x2 * x2 + y2 * y2, x3 * x3 + y3 * y3
        ccx = (s1 * (y2 - y3) + s2 * (y3 - y1) + s3 * (y1 - y2)) / d
        ccy = (s1 * (x3 - x2) + s2 * (x1 - x3) + s3 * (x2 - x1)) / d
        cr = np.hypot(x1 - ccx, y1 - ccy)
        res = np.abs(np.hypot(xs[None, :] - ccx[:, None], ys[None, :] - ccy[:, None]) - cr[:, None])
        votes = np.where(ok, (res < 1.5).sum(axis=1), -1)
        inliers = res[int(np.argmax(votes))] < 1.5
        if inliers.sum() < 30:
            return None
        fitted = _circle_through(xs[inliers], ys[inliers])
        if fitted is None:
            return None
        c = fitted
    return c


def _support(gx: np.ndarray, gy: np.ndarray, c: Circle, strong: float) -> tuple[float, float]:
    """(share of the circle's visible arc with a radial edge on it, share of the circle visible)."""
    _, _, g, inside = _radial_edges(gx, gy, c, 1)
    visible = float(inside.mean())
    return (float((g[inside] > strong).mean()) if inside.any() else 0.0), visible


def find_mirror_rim(bgr: np.ndarray) -> Circle | None:
    """The mirror's rim in an omnidirectional picture, from its edges (not from brightness): the
    largest circle along which the picture has a radial edge on most of its visible arc.

    Works whatever surrounds the mirror (black, grey, a lit room), under vignetting, and when the
    picture's edge cuts the rim (the arc inside the picture decides). Candidates come from a
    Hough transform; each is refined on the edges near it (RANSAC, then least squares) and kept
    if a radial edge runs along at least ``RIM_MIN_SUPPORT`` of its visible arc; the largest
    kept is the rim (the floor's horizon and the leader's own body are circles inside it)."""
    img = np.asarray(bgr)
    grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
    blur = cv2.GaussianBlur(grey, (0, 0), 1.5)
    gx = cv2.Sobel(blur, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(blur, cv2.CV_32F, 0, 1, ksize=3)
    strong = max(20.0, 0.5 * float(np.percentile(np.hypot(gx, gy), 90)))
    h, w = grey.shape[:2]
    found = cv2.HoughCircles(blur, cv2.HOUGH_GRADIENT, dp=2, minDist=4, param1=80, param2=20,
                             minRadius=int(0.25 * min(h, w)), maxRadius=int(0.75 * max(h, w)))
    if found is None:
        return None
    seeds: dict[tuple[int, int, int], Circle] = {}
    for cx, cy, r in found[0][:40]:  # near-duplicates refine to the same circle: once each
        seeds.setdefault((int(cx // 6), int(cy // 6), int(r // 6)), Circle(float(cx), float(cy), float(r)))
    rng = np.random.default_rng(0)
    kept: list[Circle] = []
    for seed in seeds.values():
        c = _refine(gx, gy, seed, strong, rng)
        if c is None or not 0.2 * min(h, w) <= c.radius <= max(h, w):
            continue
        share, visible = _support(gx, gy, c, strong)
        if share >= RIM_MIN_SUPPORT and visible >= RIM_MIN_VISIBLE:
            kept.append(c)
    return max(kept, key=lambda c: c.radius) if kept else None


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

