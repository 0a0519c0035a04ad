"""Obstacles from the omnidirectional image: a polar free-space scan, a laser scan from the camera.

Along each bearing, from the edge of the leader's body outward to the working area's outer
radius (paper fig. 8), the scan finds the first pixel that is not floor and is not a tracked
follower, and turns its image radius into a ground distance through Γ. The image is sampled
once on a polar grid (rows: image angles, columns: radii; one ``cv2.remap`` with maps made at
construction), so a frame costs a remap of about 50,000 samples, two passes over them, a
morphological opening and a few array passes.

Floor. The floor is what most of the working ring shows: each frame, the median of the
ring's colours (lightness (B + G + R) / 3 and two chroma axes R − G, B − G) is the floor's colour and their median absolute deviation its
spread, so the model follows the lighting as it drifts. A pixel is not floor when its
lightness or its chroma lies further from the floor's than ``lightness_k`` / ``chroma_k``
spreads (with floors on the spreads). The opening of the result (3 degrees by 5 samples outward
on the polar grid) removes thin lines a floor has (tile grout, thick near the camera, also
where it runs along a ray) and single pixels; ``min_run_px`` samples in a row outward then make a hit.

Ground distance. Γ maps a pixel to the distance of a point at the calibration markers'
height h_m (docs/calibration.md: the markers stand on the followers); the foot of an
obstacle's face stands on the floor, which the same ray meets further out: ρ_floor =
ρ_Γ · H / (H − h_m), H the mirror's viewpoint height.

Followers. Each tracked follower (its estimated position p, leader frame) covers in the
image its footprint (a disc of radius R: its body, with margins for its estimate and the
blur) and its top, which the mirror shows where the same rays meet the floor: p scaled by
H / (H − h_f) about the leader. Samples inside the capsule joining the two are not
obstacles; an obstacle behind it cannot be seen: those bearings are marked hidden and the
memory keeps what it knew there. The region is kept tight on purpose: an obstacle next to
a follower must stay visible.

Memory. Obstacle points that leave the ring or are hidden behind a follower are kept for
``keep_s`` seconds in the odometry frame of the leader (eq. 38: the displacements the
pipeline integrates), one point per 5 cm cell; a remembered point the scan now sees as free
floor is forgotten at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from core.camera.config import WorkingArea
from core.camera.gamma import Gamma
from core.geometry import leader_to_world, world_to_leader
from core.jit import kernel
from core.types import BoolArray, FloatArray, Image

if TYPE_CHECKING:
    from core.camera.render.renderer import Scratch


@dataclass(frozen=True)
class ScanSettings:
    """The scan's parameters (SI units, pixels where said)."""

    mirror_height_m: float = 0.55  # H: the mirror's viewpoint above the floor
    marker_height_m: float = 0.102  # h_m: the height Γ was calibrated at (the markers on the followers)
    follower_height_m: float = 0.10  # h_f
    follower_body_m: float = 0.21  # R: a follower's body (15 x 25 cm: half-diagonal 0.146 m), its estimate's error, the blur
    follower_radius_m: float = 0.24  # the memory forgets what it kept this near a follower (see ObstacleMemory.update)
    leader_radius_m: float = 0.25  # the leader's body: the scan starts beyond it (and 3 cm more: its edge blurs)
    rows: int = 360  # image angles sampled (1 degree)
    bin_deg: float = 1.0  # the published scan's bearing step
    lightness_k: float = 4.0
    chroma_k: float = 4.0
    min_lightness: float = 30.0  # floors on the spreads (8-bit grey levels)
    min_chroma: float = 9.0
    min_run_px: int = 2
    keep_s: float = 3.0  # memory of obstacles out of sight
    cell_m: float = 0.05  # memory resolution


@dataclass(frozen=True)
class Scan:
    """One frame's scan, leader frame, in bearing bins of ``bin_deg`` from −180°."""

    bearings: FloatArray  # (B,) rad, bin centres
    ranges: FloatArray  # (B,) m to the first obstacle; inf: free as far as the ring reaches
    reach: FloatArray  # (B,) m the ring reaches along the bin (NaN: no row fell in it)
    hidden: BoolArray  # (B,) a tracked follower hides what lies behind it
    min_range_m: float  # nothing nearer than this can be seen (the leader's body, the ring's inner edge)

    def points(self) -> FloatArray:
        """(k, 2) leader-frame points of the hits."""
        hit = np.isfinite(self.ranges)
        r, b = self.ranges[hit], self.bearings[hit]
        return np.column_stack([-r * np.sin(b), r * np.cos(b)])


@kernel
def floor_model(bgr: np.ndarray, step: int) -> np.ndarray:
    """The floor's colour and spread from every ``step``-th sample of the polar grid, each way:
    (6,) the medians of lightness (B + G + R) / 3 and of the chroma axes R − G and B − G, then
    their median absolute deviations. Exact, from counts: every feature, and every median and
    deviation of them, is a whole number of sixths (lightness) or halves (chroma), so histograms
    of whole numbers give them all without sorting."""
    rows, cols = bgr.shape[0], bgr.shape[1]
    ys = range(0, rows, step)
    xs = range(0, cols, step)
    n = len(ys) * len(xs)
    out = np.zeros(6)
    if n == 0:
        return out
    whole = np.empty((3, n), np.int64)  # per feature, the whole number counted: B + G + R, R − G + 255, B − G + 255
    k = 0
    for i in ys:
        for j in xs:
            b, g, r = np.int64(bgr[i, j, 0]), np.int64(bgr[i, j, 1]), np.int64(bgr[i, j, 2])
            whole[0, k] = b + g + r
            whole[1, k] = r - g + 255
            whole[2, k] = b - g + 255
            k += 1
    scale = (3.0, 1.0, 1.0)  # lightness is the sum / 3
    offset = (0.0, 255.0, 255.0)
    for f in range(3):
        hist = np.zeros(766, np.int64)
        for v in whole[f]:
            hist[v] += 1
        m2 = _twice_median(hist, n)  # twice the median, in whole numbers
        dev = np.zeros(2 * 766, np.int64)  # |2 x − 2 median|
        for v in whole[f]:
            dev[abs(2 * v - m2)] += 1
        out[f] = m2 / (2.0 * scale[f]) - offset[f]
        out[3 + f] = _twice_median(dev, n) / (4.0 * scale[f])
    return out


@kernel
def _twice_median(hist: np.ndarray, n: int) -> int:
    """Twice the median of ``n`` whole numbers given as counts per value (the two middle ones
    added when ``n`` is even)."""
    lo = (n - 1) // 2  # the middle ranks, 0-based
    hi = n // 2
    seen = 0
    a = -1
    for v in range(hist.shape[0]):
        seen += hist[v]
        if a < 0 and seen > lo:
            a = v
        if seen > hi:
            return a + v
    return 2 * a


@kernel
def _not_floor(bgr: np.ndarray, l0: float, a0: float, b0: float, light: float, chroma2: float) -> np.ndarray:
    """uint8 (rows, J): 1 where the sample's lightness or chroma is far from the floor's."""
    rows, cols = bgr.shape[0], bgr.shape[1]
    out = np.zeros((rows, cols), np.uint8)
    for i in range(rows):
        for j in range(cols):
            b, g, r = float(bgr[i, j, 0]), float(bgr[i, j, 1]), float(bgr[i, j, 2])
            da = r - g - a0
            db = b - g - b0
            if abs((b + g + r) / 3.0 - l0) > light or da * da + db * db > chroma2:
                out[i, j] = 1
    return out


@kernel
def _first_runs(not_floor: np.ndarray, ground: np.ndarray, run: int) -> np.ndarray:
    """(rows,) ground distance where each row's first run of ``run`` non-floor samples starts; inf: none."""
    rows, cols = not_floor.shape[0], not_floor.shape[1]
    out = np.full(rows, np.inf)
    for i in range(rows):
        count = 0
        for j in range(cols):
            if not_floor[i, j]:
                count += 1
                if count == run:
                    out[i] = ground[i, j - run + 1]
                    break
            else:
                count = 0
    return out


_WRAP = 2  # rows of the polar grid repeated at each end (half the opening's height, and one more)


def _in_capsule(xy: FloatArray, x: float, y: float, squash: float, radius: float) -> BoolArray:
    """(rows, J) whether each sample (rows, J, 2) lies in the image of a follower at (x, y):
    its footprint (a disc of ``radius``) and its top, which the mirror shows where the same
    rays meet the floor, scaled by ``squash`` about the leader — together the capsule from
    (x, y) to squash·(x, y), its radius growing from ``radius`` to squash·``radius``."""
    px, py = xy[..., 0], xy[..., 1]
    ex, ey = (squash - 1.0) * x, (squash - 1.0) * y
    t = np.clip(((px - x) * ex + (py - y) * ey) / max(ex * ex + ey * ey, 1e-12), 0.0, 1.0)
    d = np.hypot(px - (x + t * ex), py - (y + t * ey))
    return np.asarray(d <= radius * (1.0 + t * (squash - 1.0)))


def _wrap(a: FloatArray) -> FloatArray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class FreeSpaceScanner:
    """Precomputes the polar grid of one rig (Γ and working area); ``scan`` per frame."""

    def __init__(self, gamma: Gamma, area: WorkingArea, settings: ScanSettings = ScanSettings()) -> None:
        self.settings = s = settings
        r0 = max(float(area.inner_px), gamma.r_min_px, 1.0)  # Γ is not extrapolated inward: it bends fast there
        radii = np.arange(r0, float(area.outer_px), 1.0)
        # the grid wraps round: _WRAP rows either side repeat the other end's, so the opening
        # treats the first and last image angles as the neighbours they are
        psi = (np.arange(s.rows + 2 * _WRAP) - _WRAP) * (2 * np.pi / s.rows)
        self.map_x = (gamma.cx + np.cos(psi)[:, None] * radii[None, :]).astype(np.float32)
        self.map_y = (gamma.cy + np.sin(psi)[:, None] * radii[None, :]).astype(np.float32)
        core = slice(_WRAP, _WRAP + s.rows)
        rng, bearing = gamma.range_bearing(self.map_x[core].astype(np.float64), self.map_y[core].astype(np.float64))
        scale = s.mirror_height_m / (s.mirror_height_m - s.marker_height_m)
        self.ground = np.asarray(rng, dtype=np.float64) * scale  # (rows, J) floor distance of each sample
        self.row_bearing = _wrap(np.asarray(bearing, dtype=np.float64)[:, len(radii) // 2])  # (rows,)
        self._beyond_body = (self.ground >= s.leader_radius_m + 0.03).astype(np.uint8)
        self._beyond_body[:, :3] = 0  # the opening cannot judge the grid's first and last samples (no neighbours)
        self._beyond_body[:, -2:] = 0
        b = np.asarray(bearing, dtype=np.float64)
        self.sample_xy = np.stack([-self.ground * np.sin(b), self.ground * np.cos(b)], axis=-1)  # (rows, J, 2) leader frame
        self.min_range_m = float(np.nanmin(np.where(self._beyond_body > 0, self.ground, np.inf)))
        n_bins = int(round(360.0 / s.bin_deg))
        self.bin_bearings: FloatArray = -np.pi + (np.arange(n_bins, dtype=np.float64) + 0.5) * math.radians(s.bin_deg)
        self.row_bin = np.floor((self.row_bearing + np.pi) / math.radians(s.bin_deg)).astype(np.int64) % n_bins
        reach = np.full(n_bins, np.nan)
        np.fmax.at(reach, self.row_bin, self.ground[:, -1])
        self.bin_reach = reach
        self._kernel = np.ones((3, 5), np.uint8)  # 3 rows (degrees) by 5 samples outward
        self._by_bin = np.argsort(self.row_bin, kind="stable")  # rows grouped by bin, for reduceat
        self._bins_present, self._bin_starts = np.unique(self.row_bin[self._by_bin], return_index=True)
        self._crops: dict[tuple[int, ...], tuple[slice, slice, np.ndarray, np.ndarray]] = {}
        self._scratch: Scratch | None = None  # the arrays a synthetic frame's ring is rendered in (renderer.Scratch)
        self._polar: np.ndarray | None = None  # the polar grid's samples, kept from scan to scan

    def _crop(self, shape: tuple[int, ...]) -> tuple[slice, slice, np.ndarray, np.ndarray]:
        """(rows, columns, map_x, map_y) for a frame of ``shape``: the rectangle of the image
        the grid samples (the working ring's square, about half a 640 x 480 frame: an image
        that makes its pixels when looked at makes only those) and the maps moved onto it. Every
        sample inside the image lies inside the rectangle (2 pixels spare for the remap's
        rounding) and every one outside it stays outside, so the polar grid is the whole frame's."""
        crop = self._crops.get(shape)
        if crop is None:
            h, w = int(shape[0]), int(shape[1])
            x0 = min(max(0, int(np.floor(self.map_x.min())) - 2), w)
            y0 = min(max(0, int(np.floor(self.map_y.min())) - 2), h)
            x1 = max(min(w, int(np.ceil(self.map_x.max())) + 3), x0)
            y1 = max(min(h, int(np.ceil(self.map_y.max())) + 3), y0)
            if x1 <= x0 or y1 <= y0:  # the ring wholly outside the image: every sample is the border's
                x0 = y0 = 0
                x1, y1 = w, h
            crop = self._crops[shape] = (slice(y0, y1), slice(x0, x1), self.map_x - np.float32(x0),
                                         self.map_y - np.float32(y0))
        return crop

    def scan(self, frame: Image, followers: FloatArray | None = None, tracked: BoolArray | None = None) -> Scan:
        """The scan of one BGR frame; ``followers`` (n, 2) estimated positions (leader frame) of
        the ``tracked`` followers, whose bodies are not obstacles."""
        return self.scan_samples(self.sample(frame), followers, tracked)

    def sample(self, frame: Image) -> np.ndarray:
        """The frame's samples on the polar grid (rows: image angles, columns: radii; BGR), the
        first half of :meth:`scan` (about half its time: a synthetic frame renders the ring
        here). The array is the scanner's own, overwritten by its next ``sample``."""
        rows_, cols_, map_x, map_y = self._crop(tuple(frame.shape))
        region = getattr(frame, "region", None)  # a synthetic frame renders the ring into this scanner's arrays
        if region is not None and self._scratch is None:
            from core.camera.render.renderer import Scratch  # loaded already: the frame is one of its

            self._scratch = Scratch()
        crop = region(rows_, cols_, self._scratch) if region is not None else np.asarray(frame[rows_, cols_])
        if self._polar is None or self._polar.shape != map_x.shape + (3,):
            self._polar = np.empty(map_x.shape + (3,), np.uint8)
        # into the scanner's own grid, whatever the camera (a fresh one each scan came page by page from the system)
        return np.asarray(cv2.remap(crop, map_x, map_y, cv2.INTER_NEAREST, dst=self._polar, borderValue=(0, 0, 0)))

    def scan_samples(self, polar: np.ndarray, followers: FloatArray | None = None,
                     tracked: BoolArray | None = None) -> Scan:
        """The scan of a frame's samples on the polar grid (:meth:`sample`), the second half of :meth:`scan`."""
        s = self.settings
        model = floor_model(polar, 4)  # the floor's colour: medians; its spread: their MADs
        spread = model[3:] * 1.4826
        sl = max(s.min_lightness, s.lightness_k * float(spread[0]))
        sc = max(s.min_chroma, s.chroma_k * float(spread[1] + spread[2]))
        not_floor_u8 = _not_floor(polar, float(model[0]), float(model[1]), float(model[2]), sl, sc * sc)
        # thin lines (tile grout along a ray) and single pixels are not obstacles: an opening
        # three samples wide in angle and in radius removes them
        opened = cv2.morphologyEx(not_floor_u8, cv2.MORPH_OPEN, self._kernel)
        not_floor = opened[_WRAP: _WRAP + s.rows] * self._beyond_body
        hidden_rows = np.zeros(s.rows, dtype=bool)
        if followers is not None:
            pts = np.asarray(followers, dtype=np.float64).reshape(-1, 2)
            keep = np.isfinite(pts).all(axis=1)
            if tracked is not None:
                keep &= np.asarray(tracked, dtype=bool)
            squash = s.mirror_height_m / (s.mirror_height_m - s.follower_height_m)
            for x, y in pts[keep]:
                rho = math.hypot(x, y)
                if rho <= 1e-6:
                    continue
                reach = s.follower_body_m * squash
                rows = np.nonzero(np.abs(_wrap(self.row_bearing - math.atan2(-x, y))) <= math.asin(min(1.0, reach / rho)))[0]
                if len(rows) == 0:
                    continue
                # only the samples between its near side and its top's far side (a few more for Γ's sectors)
                profile = self.ground[rows[len(rows) // 2]]
                j0 = max(int(np.searchsorted(profile, rho - s.follower_body_m)) - 3, 0)
                j1 = int(np.searchsorted(profile, (rho + s.follower_body_m) * squash)) + 3
                inside = _in_capsule(self.sample_xy[rows, j0:j1], x, y, squash, s.follower_body_m)
                not_floor[rows, j0:j1] *= ~inside
                hidden_rows[rows[inside.any(axis=1)]] = True
        row_range = _first_runs(not_floor, self.ground, s.min_run_px)
        ranges = np.full(self.bin_bearings.shape[0], np.inf)
        ranges[self._bins_present] = np.minimum.reduceat(row_range[self._by_bin], self._bin_starts)
        hidden = np.zeros(self.bin_bearings.shape[0], dtype=bool)
        hidden[self._bins_present] = np.logical_or.reduceat(hidden_rows[self._by_bin], self._bin_starts)
        return Scan(self.bin_bearings, ranges, self.bin_reach, hidden, self.min_range_m)


@dataclass
class ObstacleMemory:
    """Obstacle points in the leader's odometry frame (eq. 38), kept while out of sight."""

    settings: ScanSettings = ScanSettings()
    pose: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, math.pi / 2]))  # odometry frame
    points: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))  # odometry frame
    seen_at: FloatArray = field(default_factory=lambda: np.zeros(0))

    def move(self, displacement: tuple[float, float, float]) -> None:
        """The leader moved by (dx, dy, γ) in its old frame (leader odometry, eq. 38)."""
        dx, dy, g = displacement
        phi = float(self.pose[2]) - math.pi / 2
        c, s = math.cos(phi), math.sin(phi)
        self.pose = np.array([self.pose[0] + c * dx - s * dy, self.pose[1] + s * dx + c * dy, self.pose[2] + g])

    def _to_leader(self, pts: FloatArray, pose: FloatArray | None = None) -> FloatArray:
        """Odometry-frame points in the leader's frame at ``pose`` (its pose now when None)."""
        pose = self.pose if pose is None else pose
        return world_to_leader(pts, pose[:2], float(pose[2]))

    def _to_odometry(self, pts: FloatArray, pose: FloatArray | None = None) -> FloatArray:
        """Points of the leader's frame at ``pose`` (its pose now when None) in the odometry frame."""
        pose = self.pose if pose is None else pose
        return leader_to_world(pts, pose[:2], float(pose[2]))

    def current(self, t: float) -> FloatArray:
        """(k, 2) leader-frame points known now without a new scan (between scans: what the
        last one saw and what is remembered, moved by the odometry since)."""
        fresh = self.seen_at >= t - self.settings.keep_s
        return self._to_leader(self.points[fresh]) if fresh.any() else np.zeros((0, 2))

    def update(self, scan: Scan, t: float, followers: FloatArray | None = None,
               pose: FloatArray | None = None) -> FloatArray:
        """Take the scan of the frame of time t; (k, 2) obstacle points in the leader's frame of
        that frame: the scan's hits and what is remembered where the scan cannot see. ``followers``:
        (n, 2) positions of the tracked followers (that frame's leader frame): what was remembered
        where one stands was that follower (seen before it was tracked) or is hidden under it.
        ``pose``: the odometry pose the leader had at that frame, when the memory has moved since
        (a scan finished a tick after its frame); None: the frame is the newest."""
        s = self.settings
        now = scan.points()
        old = self._to_leader(self.points, pose) if len(self.points) else np.zeros((0, 2))
        keep = self.seen_at >= t - s.keep_s
        if followers is not None and len(old):
            f = np.asarray(followers, dtype=np.float64).reshape(-1, 2)
            f = f[np.isfinite(f).all(axis=1)]
            if len(f):
                d = np.hypot(old[:, None, 0] - f[None, :, 0], old[:, None, 1] - f[None, :, 1]).min(axis=1)
                keep &= d > s.follower_radius_m
        if len(old):
            rho = np.hypot(old[:, 0], old[:, 1])
            b = np.floor((np.arctan2(-old[:, 0], old[:, 1]) + np.pi) / math.radians(s.bin_deg)).astype(np.int64)
            b %= scan.bearings.shape[0]
            reach = scan.reach[b]
            in_view = (rho >= scan.min_range_m) & np.isfinite(reach) & (rho <= reach) & ~scan.hidden[b]
            keep &= ~in_view  # in view: the scan says what is there now (its hits are added below)
        merged = np.vstack([old[keep], now])
        times = np.concatenate([self.seen_at[keep], np.full(len(now), t)])
        if len(merged):  # one point per cell, the newest
            cells = np.floor(self._to_odometry(merged, pose) / s.cell_m).astype(np.int64)
            order = np.argsort(-times, kind="stable")
            _, first = np.unique(cells[order], axis=0, return_index=True)
            pick = order[first]
            merged, times = merged[pick], times[pick]
        self.points = self._to_odometry(merged, pose) if len(merged) else np.zeros((0, 2))
        self.seen_at = times
        return merged
