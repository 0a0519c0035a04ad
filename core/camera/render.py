"""Synthetic omnidirectional frames: what the leader's camera sees, given the team's state.

Everything that does not change from frame to frame is computed once in
:class:`Renderer`: every pixel's view ray, where it meets the floor (leader frame) or
the distant walls, the floor and wall textures and a bank of sensor noise. A frame is
then one compiled pass over the pixels (floor texture moved by the leader's pose,
lighting gain applied), the robots and boxes drawn as projected polygons (painter's
order, far to near), a slight blur, sensor noise and, optionally, a JPEG round trip.

Randomness only through the ``numpy.random.Generator`` the caller passes (noise, per
frame) and ``texture_seed`` (the world's look, fixed at construction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.camera.model import CameraModel
from core.jit import kernel
from core.types import BoolArray, FloatArray

# One hue per follower, as far apart as the first few allow (degrees, OpenCV hue x 2).
DEFAULT_HUES_DEG: tuple[float, ...] = (0.0, 120.0, 240.0, 60.0, 300.0, 180.0, 30.0, 270.0)

_TEX_PPM = 100.0  # floor texture: pixels per metre (1 cm texels)
_FLOOR_TEXELS = 256  # the floor texture repeats every 2.56 m (a power of two: wrapping is a mask)
_WALL_HEIGHT_M = 2.5
_WALL_COLS = 1024
_WALL_ROWS = 128
_SUBPIXEL_BITS = 4  # polygon vertices with 1/16 pixel precision
_NOISE_SLACK_ROWS = 64



@dataclass(frozen=True)
class BoxLook:
    """A robot-like box: a body and, optionally, one coloured rectangle on top."""

    length_m: float = 0.25  # along the heading (paper: 15 x 25 cm, 10 cm high)
    width_m: float = 0.15
    height_m: float = 0.10
    top_length_m: float = 0.18
    top_width_m: float = 0.11


@dataclass(frozen=True)
class RenderSettings:
    """How the synthetic camera's pictures look (static_config/camera/*.toml, [render])."""

    hues_deg: tuple[float, ...] = DEFAULT_HUES_DEG
    marker_saturation: float = 0.85
    marker_value: float = 0.85
    follower: BoxLook = BoxLook()
    noise_sigma: float = 3.0  # sensor noise, grey levels (sigma)
    blur_sigma_px: float = 0.7  # optics; 0 = none
    jpeg_quality: int = 0  # 0 = no JPEG round trip; 1..100 = quality
    drift_gain: float = 0.12  # lighting: gain varies by +- this fraction
    drift_offset: float = 6.0  # and brightness by +- this many grey levels
    drift_period_s: float = 37.0
    clutter: bool = True  # grey boxes on the floor (every clutter_period_m, repeating)
    distractor: bool = True  # a coloured box that is not a robot
    distractor_hue_deg: float = 150.0
    clutter_period_m: float = 4.0
    floor_far_m: float = 4.0  # where the floor meets the walls
    texture_seed: int = 7


def marker_bgr(hue_deg: float, saturation: float, value: float) -> tuple[float, float, float]:
    """BGR (0..255 floats) of a marker colour."""
    hsv = np.array([[[hue_deg / 2.0 % 180.0, saturation * 255.0, value * 255.0]]], dtype=np.float32)
    bgr = cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2BGR)[0, 0]
    return float(bgr[0]), float(bgr[1]), float(bgr[2])


@dataclass(frozen=True)
class SceneObject:
    """One box in the leader frame: centre (x, y), heading a (rad, from +x), colours."""

    x: float
    y: float
    a: float
    look: BoxLook
    body_bgr: tuple[float, float, float]
    top_bgr: tuple[float, float, float] | None


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma: float, amplitude: float) -> FloatArray:
    n = rng.standard_normal(shape).astype(np.float32)
    n = cv2.GaussianBlur(n, (0, 0), sigma)
    n /= max(float(np.std(n)), 1e-6)
    return n * amplitude


def _floor_texture(rng: np.random.Generator) -> np.ndarray:
    """A tiled floor, low in saturation (a grey-beige, as in a lab), repeating every 2.56 m."""
    size = _FLOOR_TEXELS
    tile = 32  # 32 cm tiles
    base = np.array([148.0, 156.0, 164.0], dtype=np.float32)
    tiles = rng.normal(0.0, 7.0, (size // tile, size // tile)).astype(np.float32)
    per_tile = np.kron(tiles, np.ones((tile, tile), np.float32))
    grain = _smooth_noise(rng, (size, size), 2.0, 5.0)
    shade = per_tile + grain
    yy, xx = np.mgrid[0:size, 0:size]
    grout = ((xx % tile) < 1) | ((yy % tile) < 1)
    shade[grout] -= 40.0
    tex = np.clip(base[None, None, :] + shade[:, :, None], 0, 255).astype(np.uint8)
    return tex


def _wall_texture(rng: np.random.Generator) -> np.ndarray:
    """Distant walls around 360 degrees: doors, cupboards, windows; greys and beiges."""
    tex = np.empty((_WALL_ROWS, _WALL_COLS, 3), np.float32)
    tex[:] = (170.0, 176.0, 182.0)
    skirting = int(_WALL_ROWS * 0.1 / _WALL_HEIGHT_M) + 1
    tex[:skirting] = (90.0, 92.0, 95.0)
    col = 0
    while col < _WALL_COLS:
        width = int(rng.integers(40, 140))
        kind = rng.integers(0, 4)
        top = int(_WALL_ROWS * rng.uniform(0.5, 0.85))
        shade = {0: (120.0, 125.0, 132.0), 1: (200.0, 204.0, 206.0), 2: (95.0, 105.0, 118.0), 3: (150.0, 150.0, 150.0)}[int(kind)]
        if kind != 3:
            tex[skirting:top, col + 4:min(col + width - 4, _WALL_COLS)] = shade
        col += width
    tex += _smooth_noise(rng, (_WALL_ROWS, _WALL_COLS), 1.5, 4.0)[:, :, None]
    return np.clip(tex, 0, 255).astype(np.uint8)


@kernel
def _background_kernel(
    floor_idx: np.ndarray, fx: np.ndarray, fy: np.ndarray,
    wall_idx: np.ndarray, az: np.ndarray, wall_row: np.ndarray, body_idx: np.ndarray,
    leader_x: float, leader_y: float, phi: float,
    floor_tex: np.ndarray, wall_tex: np.ndarray, body: np.ndarray, ppm: float,
    gain: float, offset: float, out: np.ndarray,
) -> None:
    """One pass over the pixels that change: floor texture under the leader's pose, walls, body.

    ``out`` is the frame as (H*W, 3); pixels beyond the mirror's rim are left as they are.
    The floor texture's side is a power of two, so wrapping is a bit mask.
    """
    lut = np.empty(256, np.uint8)
    for v in range(256):
        val = v * gain + offset
        lut[v] = 255 if val > 255.0 else (0 if val < 0.0 else np.uint8(val))
    c = math.cos(phi)
    s = math.sin(phi)
    mask = floor_tex.shape[0] - 1
    # texel coordinates kept positive so truncation is floor and wrapping a bit mask
    bias = float(1 << 24)
    ox = leader_x * ppm + bias
    oy = leader_y * ppm + bias
    cp = c * ppm
    sp = s * ppm
    for k in range(floor_idx.shape[0]):
        i = int(sp * fx[k] + cp * fy[k] + oy) & mask
        j = int(cp * fx[k] - sp * fy[k] + ox) & mask
        q = floor_idx[k]
        out[q, 0] = lut[floor_tex[i, j, 0]]
        out[q, 1] = lut[floor_tex[i, j, 1]]
        out[q, 2] = lut[floor_tex[i, j, 2]]
    wcols = wall_tex.shape[1]  # a power of two
    wmask = wcols - 1
    shift = (phi / (2.0 * math.pi)) % 1.0 * wcols
    for k in range(wall_idx.shape[0]):
        j = int(az[k] + shift) & wmask
        i = wall_row[k]
        q = wall_idx[k]
        out[q, 0] = lut[wall_tex[i, j, 0]]
        out[q, 1] = lut[wall_tex[i, j, 1]]
        out[q, 2] = lut[wall_tex[i, j, 2]]
    for k in range(body_idx.shape[0]):
        q = body_idx[k]
        out[q, 0] = lut[body[0]]
        out[q, 1] = lut[body[1]]
        out[q, 2] = lut[body[2]]


def _box_outlines(objs: list[SceneObject]) -> tuple[FloatArray, FloatArray]:
    """Leader-frame 3-D points along every object's body edges (bottom and top rectangle,
    4 per edge) and its marker's edges (6 per edge), for all objects at once: (n, 32, 3), (n, 24, 3)."""
    n = len(objs)
    x = np.array([o.x for o in objs])
    y = np.array([o.y for o in objs])
    a = np.array([o.a for o in objs])
    dims = np.array([(o.look.length_m, o.look.width_m, o.look.height_m, o.look.top_length_m, o.look.top_width_m)
                     for o in objs]).reshape(n, 5)
    fwd = np.stack([np.cos(a), np.sin(a)], axis=-1)  # (n, 2)
    left = np.stack([-np.sin(a), np.cos(a)], axis=-1)
    unit = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])  # (corner, (along, across))

    def outline(length: FloatArray, width: FloatArray, per_edge: int) -> FloatArray:
        f = np.arange(per_edge) / per_edge
        c0 = unit
        c1 = np.roll(unit, -1, axis=0)
        local = (c0[:, None, :] * (1 - f)[None, :, None] + c1[:, None, :] * f[None, :, None]).reshape(-1, 2)
        along = local[None, :, 0] * length[:, None]
        across = local[None, :, 1] * width[:, None]
        px = x[:, None] + along * fwd[:, None, 0] + across * left[:, None, 0]
        py = y[:, None] + along * fwd[:, None, 1] + across * left[:, None, 1]
        return np.stack([px, py], axis=-1)

    body2 = outline(dims[:, 0], dims[:, 1], 4)  # (n, 16, 2)
    zeros = np.zeros(body2.shape[:2] + (1,))
    heights = np.broadcast_to(dims[:, 2, None, None], zeros.shape)
    body = np.concatenate([np.concatenate([body2, zeros], axis=-1),
                           np.concatenate([body2, heights], axis=-1)], axis=1)
    top2 = outline(dims[:, 3], dims[:, 4], 6)
    top = np.concatenate([top2, np.broadcast_to(dims[:, 2, None, None] + 0.002, top2.shape[:2] + (1,))], axis=-1)
    return body, top


class Renderer:
    """Synthetic frames from one camera model; precomputes everything static at construction."""

    def __init__(self, model: CameraModel, settings: RenderSettings = RenderSettings()) -> None:
        self.model = model
        self.settings = settings
        h, w = model.height, model.width
        self.shape = (h, w, 3)
        vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
        # sample each pixel at its centre
        pix = np.stack([uu, vv], axis=-1).reshape(-1, 2)
        d = model.pixels_to_directions(pix)
        radius = np.hypot(pix[:, 0] - model.cx, pix[:, 1] - model.cy)
        drop = -model.mirror_height_m
        down = d[:, 2] < -1e-6
        t = np.where(down, drop / np.where(down, d[:, 2], -1.0), np.inf)
        fx = t * d[:, 0]
        fy = t * d[:, 1]
        on_floor = down & (np.hypot(fx, fy) < settings.floor_far_m)
        body_px = radius <= model.body_radius_px()
        dark_px = radius > model.rim_radius_px()
        floor_px = on_floor & ~body_px & ~dark_px
        wall_px = ~on_floor & ~body_px & ~dark_px
        horiz = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        wall_z = model.mirror_height_m + settings.floor_far_m * d[:, 2] / horiz
        row = np.clip(wall_z / _WALL_HEIGHT_M * _WALL_ROWS, 0, _WALL_ROWS - 1).astype(np.int32)
        self._floor_idx = np.flatnonzero(floor_px).astype(np.int32)
        self._fx = fx[floor_px].astype(np.float32)
        self._fy = fy[floor_px].astype(np.float32)
        self._wall_idx = np.flatnonzero(wall_px).astype(np.int32)
        # azimuth in wall-texture columns, in [0, cols)
        self._az = ((np.arctan2(d[:, 1], d[:, 0])[wall_px] % (2 * np.pi)) * (_WALL_COLS / (2 * np.pi))).astype(np.float32)
        self._wall_row = row[wall_px].copy()
        self._body_idx = np.flatnonzero(body_px).astype(np.int32)
        self._template = np.full(self.shape, 6, np.uint8)  # beyond the rim: (nearly) black
        tex_rng = np.random.default_rng(settings.texture_seed)
        self._floor_tex = _floor_texture(tex_rng)
        self._wall_tex = _wall_texture(tex_rng)
        self._body = np.array([52, 50, 48], np.uint8)
        # sensor noise: two non-negative banks (added, subtracted) with spare rows to shift
        sigma = settings.noise_sigma
        bank = tex_rng.normal(0.0, sigma, (h + _NOISE_SLACK_ROWS, w, 3)) if sigma > 0 else np.zeros((h + _NOISE_SLACK_ROWS, w, 3))
        self._noise_pos = np.clip(bank, 0, 255).astype(np.uint8)
        self._noise_neg = np.clip(-bank, 0, 255).astype(np.uint8)
        self._clutter = self._make_clutter(tex_rng)
        self._marker_colours = [marker_bgr(h, settings.marker_saturation, settings.marker_value) for h in settings.hues_deg]

    # -- the world's furniture ---------------------------------------------------------

    def _make_clutter(self, rng: np.random.Generator) -> list[tuple[float, float, float, BoxLook, tuple[float, float, float], tuple[float, float, float] | None]]:
        """World-fixed boxes inside one clutter cell; the cell repeats over the floor."""
        s = self.settings
        items: list[tuple[float, float, float, BoxLook, tuple[float, float, float], tuple[float, float, float] | None]] = []
        if s.clutter:
            for _ in range(2):
                size = float(rng.uniform(0.2, 0.4))
                grey = float(rng.uniform(70, 190))
                look = BoxLook(size, float(rng.uniform(0.15, 0.3)), float(rng.uniform(0.1, 0.35)), 0.0, 0.0)
                items.append((float(rng.uniform(0, s.clutter_period_m)), float(rng.uniform(0, s.clutter_period_m)),
                              float(rng.uniform(-math.pi, math.pi)), look, (grey, grey + 3, grey + 6), None))
        if s.distractor:
            look = BoxLook(0.12, 0.12, 0.12, 0.10, 0.10)
            items.append((float(rng.uniform(0, s.clutter_period_m)), float(rng.uniform(0, s.clutter_period_m)),
                          0.0, look, marker_bgr(s.distractor_hue_deg, 0.8, 0.7),
                          marker_bgr(s.distractor_hue_deg, 0.8, 0.8)))
        return items

    def _clutter_objects(self, leader_pose: FloatArray, robots: FloatArray | None = None) -> list[SceneObject]:
        """Clutter instances within the floor's reach, in the leader frame.

        The simulator has no collisions, so an instance a robot would drive into is left
        out: none within 0.6 m of the leader or 0.45 m of a follower (``robots``, (n, 2)+).
        """
        if not self._clutter:
            return []
        period = self.settings.clutter_period_m
        lx, ly, lth = float(leader_pose[0]), float(leader_pose[1]), float(leader_pose[2])
        phi = lth - math.pi / 2
        c, s = math.cos(phi), math.sin(phi)
        reach = self.settings.floor_far_m
        objs: list[SceneObject] = []
        cells = range(-2, 3)
        cx0, cy0 = math.floor(lx / period), math.floor(ly / period)
        for wx0, wy0, wa, look, body, top in self._clutter:
            for i in cells:
                for j in cells:
                    wx = (cx0 + i) * period + wx0 - lx
                    wy = (cy0 + j) * period + wy0 - ly
                    x, y = c * wx + s * wy, -s * wx + c * wy
                    if not 0.6 < math.hypot(x, y) < reach - 0.3:
                        continue
                    if robots is not None and len(robots) and np.min(np.hypot(robots[:, 0] - x, robots[:, 1] - y)) < 0.45:
                        continue
                    objs.append(SceneObject(x, y, wa - phi, look, body, top))
        return objs

    # -- a frame -----------------------------------------------------------------------

    def lighting(self, t: float) -> tuple[float, float]:
        """(gain, offset) of the slowly drifting illumination at time t."""
        s = self.settings
        if s.drift_period_s <= 0:
            return 1.0, 0.0
        w = 2 * math.pi / s.drift_period_s
        return 1.0 + s.drift_gain * math.sin(w * t), s.drift_offset * math.sin(0.61 * w * t + 1.0)

    def follower_objects(self, followers_leader: FloatArray, hidden: BoolArray | None = None) -> list[SceneObject]:
        """Followers as boxes with their marker colours; (n, 3) rows are (x, y, a) in the leader frame."""
        s = self.settings
        objs = []
        body = (40.0, 40.0, 44.0)
        for i, (x, y, a) in enumerate(np.asarray(followers_leader, dtype=np.float64)):
            if hidden is not None and bool(hidden[i]):
                continue
            objs.append(SceneObject(float(x), float(y), float(a), s.follower, body,
                                    self._marker_colours[i % len(self._marker_colours)]))
        return objs

    def render(
        self,
        leader_pose: FloatArray,
        followers_leader: FloatArray,
        t: float,
        rng: np.random.Generator,
        hidden: BoolArray | None = None,
    ) -> np.ndarray:
        """One BGR frame (H, W, 3) uint8.

        leader_pose: the leader's world pose (x, y, theta) (moves the floor and clutter);
        followers_leader: (n, 3) follower poses (x, y, a) in the leader frame;
        hidden: followers not drawn (occluded).
        """
        gain, offset = self.lighting(t)
        out = self._template.copy()
        lp = np.asarray(leader_pose, dtype=np.float64)
        _background_kernel(
            self._floor_idx, self._fx, self._fy, self._wall_idx, self._az, self._wall_row, self._body_idx,
            float(lp[0]), float(lp[1]), float(lp[2]) - math.pi / 2,
            self._floor_tex, self._wall_tex, self._body, _TEX_PPM, gain, offset,
            out.reshape(-1, 3),
        )
        robots = np.asarray(followers_leader, dtype=np.float64).reshape(-1, 3)[:, :2]
        objs = self._clutter_objects(lp, robots) + self.follower_objects(followers_leader, hidden)
        objs.sort(key=lambda o: -math.hypot(o.x, o.y))
        if objs:
            self._draw_boxes(out, objs, gain, offset)
        s = self.settings
        if s.blur_sigma_px > 0:
            out = cv2.GaussianBlur(out, (3, 3), s.blur_sigma_px)
        if s.noise_sigma > 0:
            r0 = int(rng.integers(0, _NOISE_SLACK_ROWS))
            h = self.shape[0]
            cv2.add(out, self._noise_pos[r0:r0 + h], dst=out)
            r1 = int(rng.integers(0, _NOISE_SLACK_ROWS))
            cv2.subtract(out, self._noise_neg[r1:r1 + h], dst=out)
        if s.jpeg_quality > 0:
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(s.jpeg_quality)])
            if ok:
                out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        return out

    def _draw_boxes(self, img: np.ndarray, objs: list[SceneObject], gain: float, offset: float) -> None:
        """Draw boxes in the given order (far to near): dark body silhouette, then the marker."""
        body3, top3 = _box_outlines(objs)
        scale = float(1 << _SUBPIXEL_BITS)
        body_px = (self.model.project(body3) * scale).round()
        top_px = (self.model.project(top3) * scale).round()
        limit = 4 * scale * max(self.model.width, self.model.height)
        ok = np.all(np.isfinite(body_px) & (np.abs(body_px) < limit), axis=(1, 2))
        body_i = np.where(ok[:, None, None], body_px, 0).astype(np.int32)
        top_i = np.where(ok[:, None, None], top_px, 0).astype(np.int32)
        lut = np.clip(np.array([[o.body_bgr for o in objs]]) * gain + offset, 0, 255)[0]
        for i, obj in enumerate(objs):
            if not ok[i]:
                continue
            cv2.fillConvexPoly(img, cv2.convexHull(body_i[i]), lut[i].tolist(), cv2.LINE_AA, _SUBPIXEL_BITS)
            if obj.top_bgr is not None and obj.look.top_length_m > 0:
                colour = [min(255.0, max(0.0, c * gain + offset)) for c in obj.top_bgr]
                cv2.fillPoly(img, [top_i[i]], colour, cv2.LINE_AA, _SUBPIXEL_BITS)
