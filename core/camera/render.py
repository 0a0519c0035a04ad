"""Synthetic omnidirectional frames: what the leader's camera sees, given the team's state.

Everything that does not change from frame to frame is computed once in
:class:`Renderer`: every pixel's view ray, where it meets the floor (leader frame) or
the distant walls (kept as runs of one kind of pixel along each row), the floor and
wall textures and a bank of sensor noise. A frame is then one compiled pass over the
pixels (floor texture moved by the leader's pose, lighting applied), the robots and
boxes drawn as projected polygons (painter's order, far to near; their outlines
projected by one compiled pass for all of them), a slight blur, sensor noise and,
optionally, a JPEG round trip.

:meth:`Renderer.frame` gives a :class:`SyntheticFrame` that makes its pixels only
where it is looked at: the vision pipeline, while tracking, reads a small rectangle
around each follower, so a vision-in-the-loop simulation renders a few thousand pixels
a frame instead of 307,200. Any rectangle is bit for bit what the whole frame has
there (tested). :meth:`Renderer.render` gives the whole frame.

Randomness only through the ``numpy.random.Generator`` the caller passes (noise, per
frame, drawn when the frame is made) and ``texture_seed`` (the world's look, fixed at
construction).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from core.camera.model import CameraModel
from core.geometry import pose_floats
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
_RECT_MARGIN = 4  # pixels drawn around a rectangle of a frame and cut off (see Renderer._render_rect)



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
def _background_rect(
    spans: np.ndarray, row_spans: np.ndarray, pa: np.ndarray, pb: np.ndarray, width: int,
    y0: int, y1: int, x0: int, x1: int, leader_x: float, leader_y: float, phi: float,
    floor_tex: np.ndarray, wall_tex: np.ndarray, colours: np.ndarray, ppm: float, lut: np.ndarray,
) -> np.ndarray:
    """The pixels of rows y0..y1, columns x0..x1 before any box is drawn: floor texture under
    the leader's pose, distant walls, the leader's body, black beyond the mirror's rim.

    Each image row is a few runs of one kind of pixel: ``spans`` rows are (x_start, x_end,
    kind), those of image row y are ``spans[row_spans[y]:row_spans[y + 1]]``. Kinds: 0
    beyond the rim and 1 the leader's body (``colours`` rows, before lighting), 2 floor
    (pa, pb: where the pixel's ray meets the floor, leader frame, m), 3 wall (pa: azimuth in
    texture columns, pb: texture row); pa and pb are flat (row-major, ``width`` per row).
    The floor texture's side is a power of two, so wrapping is a bit mask; texel coordinates
    are kept positive so truncation is floor. Flat unsigned indices spare the compiled loop
    numpy's negative-index checks.
    """
    ow = x1 - x0
    out = np.empty((y1 - y0) * ow * 3, np.uint8)
    tw = floor_tex.shape[0]
    mask = np.int64(tw - 1)
    ftex = floor_tex.reshape(-1)
    ww = wall_tex.shape[1]  # a power of two
    wmask = np.int64(ww - 1)
    wtex = wall_tex.reshape(-1)
    bias = float(1 << 24)
    ox = leader_x * ppm + bias
    oy = leader_y * ppm + bias
    cp = math.cos(phi) * ppm
    sp = math.sin(phi) * ppm
    shift = (phi / (2.0 * math.pi)) % 1.0 * ww
    one = np.uint64(1)
    two = np.uint64(2)
    for y in range(y0, y1):
        base = y * width
        obase = (y - y0) * ow - x0
        for k in range(row_spans[y], row_spans[y + 1]):
            a = max(spans[k, 0], x0)
            b = min(spans[k, 1], x1)
            if a >= b:
                continue
            kind = spans[k, 2]
            if kind == 2:
                fxs = pa[base + a:base + b]
                fys = pb[base + a:base + b]
                run = out[(obase + a) * 3:(obase + b) * 3]
                for x in range(b - a):
                    fx = fxs[x]
                    fy = fys[x]
                    i = np.int64(sp * fx + cp * fy + oy) & mask
                    j = np.int64(cp * fx - sp * fy + ox) & mask
                    t = np.uint64((i * tw + j) * 3)
                    o = np.uint64(x * 3)
                    run[o] = lut[ftex[t]]
                    run[o + one] = lut[ftex[t + one]]
                    run[o + two] = lut[ftex[t + two]]
            elif kind == 3:
                azs = pa[base + a:base + b]
                rws = pb[base + a:base + b]
                run = out[(obase + a) * 3:(obase + b) * 3]
                for x in range(b - a):
                    j = np.int64(azs[x] + shift) & wmask
                    t = np.uint64((np.int64(rws[x]) * ww + j) * 3)
                    o = np.uint64(x * 3)
                    run[o] = lut[wtex[t]]
                    run[o + one] = lut[wtex[t + one]]
                    run[o + two] = lut[wtex[t + two]]
            elif kind == 0 and colours[0, 0] == colours[0, 1] == colours[0, 2]:  # beyond the rim: one grey, unlit
                out[(obase + a) * 3:(obase + b) * 3] = colours[0, 0]
            else:
                c0 = colours[kind, 0]
                c1 = colours[kind, 1]
                c2 = colours[kind, 2]
                if kind == 1:  # the body is lit; beyond the rim stays dark
                    c0 = lut[c0]
                    c1 = lut[c1]
                    c2 = lut[c2]
                for x in range(a, b):
                    o = np.uint64((obase + x) * 3)
                    out[o] = c0
                    out[o + one] = c1
                    out[o + two] = c2
    return out.reshape(y1 - y0, ow, 3)


@kernel
def _layout_boxes(
    cx: np.ndarray, cy: np.ndarray, ca: np.ndarray, cdims: np.ndarray, cbody: np.ndarray, ctop: np.ndarray,
    followers: np.ndarray, visible: np.ndarray, fdims: np.ndarray, fbody: np.ndarray, fcolours: np.ndarray,
    leader_x: float, leader_y: float, leader_theta: float, period: float, reach: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every box of a frame in the leader frame, far to near (painter's order).

    Clutter: the world-fixed boxes of one cell (cx, cy world, m; ca world heading), the
    cell repeating every ``period`` metres; the instances of the 5 x 5 cells around the
    leader that lie between 0.6 m and ``reach`` - 0.3 m from it and at least 0.45 m from
    every follower (the simulator has no collisions, so a robot would drive into them).
    Followers: (x, y, a) leader frame, the visible ones, marker colour i mod len(fcolours).
    Returns x, y, a, dims (m, 5), body colour (m, 3), marker colour (m, 3; NaN: none).
    """
    phi = leader_theta - math.pi / 2
    c = math.cos(phi)
    s = math.sin(phi)
    n = followers.shape[0]
    k = cx.shape[0]
    cap = 25 * k + n
    x = np.empty(cap)
    y = np.empty(cap)
    a = np.empty(cap)
    dims = np.empty((cap, 5))
    body = np.empty((cap, 3))
    top = np.empty((cap, 3))
    m = 0
    gx = math.floor(leader_x / period)
    gy = math.floor(leader_y / period)
    for i in range(-2, 3):
        for j in range(-2, 3):
            for q in range(k):
                wx = (gx + i) * period + cx[q] - leader_x
                wy = (gy + j) * period + cy[q] - leader_y
                bx = c * wx + s * wy
                by = -s * wx + c * wy
                d = math.hypot(bx, by)
                if not (0.6 < d < reach - 0.3):
                    continue
                clear = True
                for f in range(n):
                    if math.hypot(followers[f, 0] - bx, followers[f, 1] - by) < 0.45:
                        clear = False
                        break
                if not clear:
                    continue
                x[m] = bx
                y[m] = by
                a[m] = ca[q] - phi
                dims[m] = cdims[q]
                body[m] = cbody[q]
                top[m] = ctop[q]
                m += 1
    for f in range(n):
        if not visible[f]:
            continue
        x[m] = followers[f, 0]
        y[m] = followers[f, 1]
        a[m] = followers[f, 2]
        dims[m] = fdims
        body[m] = fbody
        top[m] = fcolours[f % fcolours.shape[0]]
        m += 1
    order = np.argsort(-np.hypot(x[:m], y[:m]), kind="mergesort")
    return x[order], y[order], a[order], dims[order], body[order], top[order]


@kernel
def _pixel_tables(
    to_mirror: np.ndarray, xi: float, gamma_px: float, cx: float, cy: float, mirror_height: float,
    body_radius_px: float, rim_radius_px: float, floor_far: float, h: int, w: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What every pixel shows, from its centre's view direction (CameraModel.pixels_to_directions,
    written out per pixel): kind (H, W) (0 beyond the mirror's rim, 1 the leader's body,
    2 floor, 3 wall) and flat (H*W,) pa, pb: for floor where the ray meets it (leader frame,
    m), for wall the azimuth in texture columns and the texture row, else 0."""
    kind = np.zeros((h, w), np.uint8)
    pa = np.zeros(h * w, np.float32)
    pb = np.zeros(h * w, np.float32)
    r = to_mirror
    drop = -mirror_height
    k1 = 1.0 - xi * xi
    cols_per_rad = _WALL_COLS / (2.0 * math.pi)
    rows_per_m = _WALL_ROWS / _WALL_HEIGHT_M
    for y in range(h):
        my = (y - cy) / gamma_px
        for x in range(w):
            radius = math.hypot(x - cx, y - cy)
            if radius > rim_radius_px:
                continue  # kind 0
            if radius <= body_radius_px:
                kind[y, x] = 1
                continue
            mx = (x - cx) / gamma_px
            r2 = mx * mx + my * my
            eta = (xi + math.sqrt(1.0 + k1 * r2)) / (r2 + 1.0)
            m0, m1, m2 = eta * mx, eta * my, eta - xi
            d0 = m0 * r[0, 0] + m1 * r[1, 0] + m2 * r[2, 0]
            d1 = m0 * r[0, 1] + m1 * r[1, 1] + m2 * r[2, 1]
            d2 = m0 * r[0, 2] + m1 * r[1, 2] + m2 * r[2, 2]
            i = y * w + x
            if d2 < -1e-6:
                t = drop / d2
                fx, fy = t * d0, t * d1
                if math.hypot(fx, fy) < floor_far:
                    kind[y, x] = 2
                    pa[i] = fx
                    pb[i] = fy
                    continue
            kind[y, x] = 3
            horiz = max(math.hypot(d0, d1), 1e-9)
            wall_z = mirror_height + floor_far * d2 / horiz
            pa[i] = (math.atan2(d1, d0) % (2.0 * math.pi)) * cols_per_rad
            pb[i] = np.int32(min(max(wall_z * rows_per_m, 0.0), _WALL_ROWS - 1.0))
    return kind, pa, pb


@kernel
def _row_spans(kind: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Runs of equal kind along each row of a (H, W) kind image: (runs (m, 3) of
    x_start, x_end, kind; (H + 1,) index of each row's first run)."""
    h, w = kind.shape
    n = 0
    for y in range(h):
        n += 1
        for x in range(1, w):
            n += kind[y, x] != kind[y, x - 1]
    runs = np.empty((n, 3), np.int64)
    first = np.empty(h + 1, np.int64)
    k = 0
    for y in range(h):
        first[y] = k
        start = 0
        for x in range(1, w + 1):
            if x == w or kind[y, x] != kind[y, x - 1]:
                runs[k, 0] = start
                runs[k, 1] = x
                runs[k, 2] = kind[y, start]
                k += 1
                start = x
    first[h] = k
    return runs, first


@kernel
def _box_polygons(
    x: np.ndarray, y: np.ndarray, a: np.ndarray, dims: np.ndarray,
    to_mirror: np.ndarray, xi: float, gamma_px: float, cx: float, cy: float, mirror_height: float,
    scale: float, limit: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every box projected into the image, for all boxes at once (eq. of core.camera.model).

    Per box: its body outline (bottom and top rectangle, 4 points per edge: 32 points) and
    its marker's outline (6 points per edge: 24 points), as pixels times ``scale`` (fixed
    point, rounded); its pixel bounding box (x0, y0, x1, y1, wide enough for anti-aliasing);
    and whether it projects at all (every point in front of the mirror and within ``limit``).
    dims per box: length, width, height, marker length, marker width (m).
    """
    m = x.shape[0]
    body = np.zeros((m, 32, 2), np.int32)
    top = np.zeros((m, 24, 2), np.int32)
    bbox = np.zeros((m, 4), np.int64)
    ok = np.ones(m, np.bool_)
    ua = np.array([0.5, -0.5, -0.5, 0.5])
    uc = np.array([0.5, 0.5, -0.5, -0.5])
    for b in range(m):
        ca = math.cos(a[b])
        sa = math.sin(a[b])
        lo_u = lo_v = 1e18
        hi_u = hi_v = -1e18
        for part in range(3):  # body bottom, body top, marker
            if part < 2:
                length, width, per = dims[b, 0], dims[b, 1], 4
                z = 0.0 if part == 0 else dims[b, 2]
            else:
                length, width, per = dims[b, 3], dims[b, 4], 6
                z = dims[b, 2] + 0.002
            for corner in range(4):
                nxt = (corner + 1) % 4
                for e in range(per):
                    f = e / per
                    along = (ua[corner] * (1.0 - f) + ua[nxt] * f) * length
                    across = (uc[corner] * (1.0 - f) + uc[nxt] * f) * width
                    px = x[b] + along * ca - across * sa
                    py = y[b] + along * sa + across * ca
                    pz = z - mirror_height
                    mx = to_mirror[0, 0] * px + to_mirror[0, 1] * py + to_mirror[0, 2] * pz
                    my = to_mirror[1, 0] * px + to_mirror[1, 1] * py + to_mirror[1, 2] * pz
                    mz = to_mirror[2, 0] * px + to_mirror[2, 1] * py + to_mirror[2, 2] * pz
                    denom = mz + xi * math.sqrt(mx * mx + my * my + mz * mz)
                    if denom <= 1e-12:
                        ok[b] = False
                        continue
                    u = (gamma_px * mx / denom + cx) * scale
                    v = (gamma_px * my / denom + cy) * scale
                    if not (abs(u) < limit and abs(v) < limit):
                        ok[b] = False
                        continue
                    k = corner * per + e
                    ui = np.int32(round(u))
                    vi = np.int32(round(v))
                    if part == 2:
                        top[b, k, 0] = ui
                        top[b, k, 1] = vi
                    else:
                        body[b, part * 16 + k, 0] = ui
                        body[b, part * 16 + k, 1] = vi
                    lo_u = min(lo_u, u)
                    hi_u = max(hi_u, u)
                    lo_v = min(lo_v, v)
                    hi_v = max(hi_v, v)
        if ok[b]:
            # anti-aliasing reaches a pixel beyond the outline
            bbox[b, 0] = int(math.floor(lo_u / scale)) - 2
            bbox[b, 1] = int(math.floor(lo_v / scale)) - 2
            bbox[b, 2] = int(math.ceil(hi_u / scale)) + 3
            bbox[b, 3] = int(math.ceil(hi_v / scale)) + 3
    return body, top, bbox, ok


@kernel
def _lit(c: float, gain: float, offset: float) -> float:
    """A colour channel under the frame's lighting: clip(c * gain + offset, 0, 255)."""
    return min(max(c * gain + offset, 0.0), 255.0)


@kernel
def _frame_layout(
    cx: np.ndarray, cy: np.ndarray, ca: np.ndarray, cdims: np.ndarray, cbody: np.ndarray, ctop: np.ndarray,
    followers: np.ndarray, visible: np.ndarray, fdims: np.ndarray, fbody: np.ndarray, fcolours: np.ndarray,
    leader_x: float, leader_y: float, leader_theta: float, period: float, reach: float,
    to_mirror: np.ndarray, xi: float, gamma_px: float, ccx: float, ccy: float, mirror_height: float,
    scale: float, limit: float, gain: float, offset: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
           np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A frame's geometry and lighting in one call: the boxes (``_layout_boxes``), their
    outlines and pixel bounds (``_box_polygons``; bounds zero where a box does not project),
    their lit colours (m, 6: body then marker, clip(c * gain + offset, 0, 255)), whether
    each has a marker, and the lighting table for grey levels (the same clip, truncated)."""
    x, y, a, dims, body, top = _layout_boxes(cx, cy, ca, cdims, cbody, ctop, followers, visible, fdims, fbody,
                                             fcolours, leader_x, leader_y, leader_theta, period, reach)
    body_px, top_px, bbox, ok = _box_polygons(x, y, a, dims, to_mirror, xi, gamma_px, ccx, ccy, mirror_height,
                                              scale, limit)
    m = x.shape[0]
    lit = np.empty((m, 6))
    has_top = np.empty(m, np.bool_)
    for b in range(m):
        if not ok[b]:
            bbox[b, :] = 0  # never drawn
        for c in range(3):
            lit[b, c] = _lit(body[b, c], gain, offset)
            lit[b, 3 + c] = _lit(top[b, c], gain, offset)
        has_top[b] = dims[b, 3] > 0 and not math.isnan(top[b, 0])
    lut = np.empty(256, np.uint8)
    for i in range(256):
        lut[i] = np.uint8(_lit(float(i), gain, offset))
    return x, y, a, dims, body, top, body_px, top_px, bbox, lit, has_top, lut


@dataclass(frozen=True)
class Boxes:
    """Boxes in the leader frame, one row each: centre (x, y), heading a (rad, from +x),
    size (length, width, height, marker length, marker width; m), body and marker colour
    (BGR 0..255; a marker colour of NaN: no marker)."""

    x: FloatArray
    y: FloatArray
    a: FloatArray
    dims: FloatArray  # (m, 5)
    body_bgr: FloatArray  # (m, 3)
    top_bgr: FloatArray  # (m, 3)

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @staticmethod
    def empty() -> "Boxes":
        z = np.zeros(0)
        return Boxes(z, z, z, np.zeros((0, 5)), np.zeros((0, 3)), np.zeros((0, 3)))


def _look_dims(look: BoxLook) -> tuple[float, float, float, float, float]:
    return (look.length_m, look.width_m, look.height_m, look.top_length_m, look.top_width_m)


@dataclass(frozen=True)
class _Scene:
    """One frame's worth of everything that varies: lighting, the leader's pose, the boxes
    projected (far to near), the sensor noise's offsets in the noise bank."""

    lut: np.ndarray  # (256,) uint8 lighting: grey level -> lit grey level
    leader: tuple[float, float, float]  # x, y, phi (the floor's rotation)
    boxes: Boxes
    body_px: np.ndarray  # (m, 32, 2) int32, fixed point
    top_px: np.ndarray  # (m, 24, 2) int32, fixed point
    bbox_list: list[tuple[int, int, int, int]]  # per box x0, y0, x1, y1 pixels; empty where it does not project
    noise_rows: tuple[int, int]
    draw_cache: dict[int, tuple[np.ndarray, list[float], np.ndarray | None, list[float]]]  # see Renderer._box_look
    lit_bgr: list[list[float]]  # per box: lit body colour, then lit marker colour (6 numbers)
    has_top: list[bool]  # per box: it has a marker


class SyntheticFrame:
    """A rendered frame whose pixels are made when they are first looked at.

    ``frame[y0:y1, x0:x1]`` renders just that rectangle (a new array, the very pixels the
    whole frame has there); ``np.asarray(frame)`` renders the whole frame once and keeps
    it. Everything random was drawn when the frame was made, so what is looked at, and in
    which order, never changes a pixel. A JPEG round trip mixes whole 8x8 blocks, so with
    JPEG on the whole frame is rendered at the first look.
    """

    def __init__(self, renderer: "Renderer", scene: _Scene) -> None:
        self._renderer = renderer
        self._scene = scene
        self._full: np.ndarray | None = None
        self.shape: tuple[int, int, int] = renderer.shape
        self.dtype = np.dtype(np.uint8)
        self.ndim = 3
        self.pixels_rendered = 0  # how many pixels were made (a region's and the whole frame's)

    def __array__(self, dtype: object = None, copy: object = None) -> np.ndarray:
        if self._full is None:
            h, w = self.shape[:2]
            self._full = self._renderer._render_rect(self._scene, 0, h, 0, w)
            self.pixels_rendered += h * w
            q = self._renderer.settings.jpeg_quality
            if q > 0:
                ok, buf = cv2.imencode(".jpg", self._full, [cv2.IMWRITE_JPEG_QUALITY, int(q)])
                if ok:
                    self._full = cv2.imdecode(buf, cv2.IMREAD_COLOR)
        return self._full if dtype is None else self._full.astype(dtype)

    def __getitem__(self, key: object) -> np.ndarray:
        rows = cols = None
        if type(key) is tuple and len(key) == 2:
            rows, cols = key
        if self._full is None and type(rows) is slice and type(cols) is slice and rows.step in (None, 1) \
                and cols.step in (None, 1) and self._renderer.settings.jpeg_quality <= 0:
            y0, y1, _ = rows.indices(self.shape[0])
            x0, x1, _ = cols.indices(self.shape[1])
            if y1 <= y0 or x1 <= x0:
                return np.empty((max(0, y1 - y0), max(0, x1 - x0), 3), np.uint8)
            self.pixels_rendered += (y1 - y0) * (x1 - x0)
            return self._renderer._render_rect(self._scene, y0, y1, x0, x1)
        return np.asarray(self)[key]  # type: ignore[index]


class Renderer:
    """Synthetic frames from one camera model; precomputes everything static at construction."""

    def __init__(self, model: CameraModel, settings: RenderSettings = RenderSettings()) -> None:
        self.model = model
        self.settings = settings
        h, w = model.height, model.width
        self.shape = (h, w, 3)
        kind, self._pa, self._pb = _pixel_tables(
            model._to_mirror, model.xi, model.gamma_px, model.cx, model.cy, model.mirror_height_m,
            model.body_radius_px(), model.rim_radius_px(), settings.floor_far_m, h, w)
        self._spans, self._row_spans = _row_spans(kind)
        tex_rng = np.random.default_rng(settings.texture_seed)
        self._floor_tex = _floor_texture(tex_rng)
        self._wall_tex = _wall_texture(tex_rng)
        self._colours = np.array([[6, 6, 6], [52, 50, 48]], np.uint8)  # beyond the rim; the leader's body
        # sensor noise: two non-negative banks (added, subtracted) with spare rows to shift
        sigma = settings.noise_sigma
        bank = tex_rng.standard_normal((h + _NOISE_SLACK_ROWS, w, 3), dtype=np.float32)
        bank *= np.float32(sigma)
        self._noise_pos = np.clip(bank, 0, 255).astype(np.uint8)
        np.negative(bank, out=bank)
        self._noise_neg = np.clip(bank, 0, 255).astype(np.uint8)
        self._clutter = self._make_clutter(tex_rng)
        self._marker_colours = np.array([marker_bgr(hue, settings.marker_saturation, settings.marker_value)
                                         for hue in settings.hues_deg]).reshape(-1, 3)
        self._follower_dims = np.array(_look_dims(settings.follower))
        self._follower_body = np.array([40.0, 40.0, 44.0])

    # -- the world's furniture ---------------------------------------------------------

    def _make_clutter(self, rng: np.random.Generator) -> Boxes:
        """World-fixed boxes inside one clutter cell (world frame); the cell repeats over the floor."""
        s = self.settings
        rows: list[tuple[float, float, float, tuple[float, float, float, float, float], tuple[float, float, float],
                         tuple[float, float, float]]] = []
        nan3 = (math.nan, math.nan, math.nan)
        if s.clutter:
            for _ in range(2):
                size = float(rng.uniform(0.2, 0.4))
                grey = float(rng.uniform(70, 190))
                look = BoxLook(size, float(rng.uniform(0.15, 0.3)), float(rng.uniform(0.1, 0.35)), 0.0, 0.0)
                rows.append((float(rng.uniform(0, s.clutter_period_m)), float(rng.uniform(0, s.clutter_period_m)),
                             float(rng.uniform(-math.pi, math.pi)), _look_dims(look), (grey, grey + 3, grey + 6), nan3))
        if s.distractor:
            look = BoxLook(0.12, 0.12, 0.12, 0.10, 0.10)
            rows.append((float(rng.uniform(0, s.clutter_period_m)), float(rng.uniform(0, s.clutter_period_m)),
                         0.0, _look_dims(look), marker_bgr(s.distractor_hue_deg, 0.8, 0.7),
                         marker_bgr(s.distractor_hue_deg, 0.8, 0.8)))
        if not rows:
            return Boxes.empty()
        return Boxes(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                     np.array([r[3] for r in rows]), np.array([r[4] for r in rows]), np.array([r[5] for r in rows]))

    def boxes(self, leader_pose: FloatArray, followers_leader: FloatArray, hidden: BoolArray | None = None,
              clutter_only: bool = False) -> Boxes:
        """The frame's boxes in the leader frame, far to near: clutter within the floor's reach
        (none within 0.6 m of the leader or 0.45 m of a follower: the simulator has no
        collisions) and the followers' boxes, (n, 3) rows (x, y, a), not the hidden ones."""
        return Boxes(*_layout_boxes(*self._layout_args(pose_floats(leader_pose), followers_leader, hidden,
                                                       clutter_only)))

    def _layout_args(self, leader: tuple[float, float, float], followers_leader: FloatArray,
                     hidden: BoolArray | None, clutter_only: bool = False) -> tuple[object, ...]:
        """The arguments of ``_layout_boxes`` for a frame; ``leader`` is its world pose (x, y, theta)."""
        cl = self._clutter
        fol = np.ascontiguousarray(np.asarray(followers_leader, dtype=np.float64).reshape(-1, 3))
        if clutter_only:
            visible = np.zeros(len(fol), dtype=np.bool_)
        elif hidden is None:
            visible = np.ones(len(fol), dtype=np.bool_)
        else:
            visible = ~np.asarray(hidden, dtype=np.bool_)[: len(fol)]
        return (cl.x, cl.y, cl.a, cl.dims, cl.body_bgr, cl.top_bgr, fol, visible, self._follower_dims,
                self._follower_body, self._marker_colours, *leader, self.settings.clutter_period_m,
                self.settings.floor_far_m)

    # -- a frame -----------------------------------------------------------------------

    def lighting(self, t: float) -> tuple[float, float]:
        """(gain, offset) of the slowly drifting illumination at time t."""
        s = self.settings
        if s.drift_period_s <= 0:
            return 1.0, 0.0
        w = 2 * math.pi / s.drift_period_s
        return 1.0 + s.drift_gain * math.sin(w * t), s.drift_offset * math.sin(0.61 * w * t + 1.0)

    def frame(
        self,
        leader_pose: FloatArray,
        followers_leader: FloatArray,
        t: float,
        rng: np.random.Generator,
        hidden: BoolArray | None = None,
    ) -> SyntheticFrame:
        """The frame at time t, its pixels made when first looked at (see SyntheticFrame).

        leader_pose: the leader's world pose (x, y, theta) (moves the floor and clutter);
        followers_leader: (n, 3) follower poses (x, y, a) in the leader frame;
        hidden: followers not drawn (occluded).
        """
        gain, offset = self.lighting(t)
        lx, ly, theta = pose_floats(leader_pose)
        layout = self._layout_args((lx, ly, theta), followers_leader, hidden)
        mdl = self.model
        scale = float(1 << _SUBPIXEL_BITS)
        x, y, a, dims, body, top, body_px, top_px, bbox, lit, has_top, lut = _frame_layout(
            *layout, mdl._to_mirror, mdl.xi, mdl.gamma_px, mdl.cx, mdl.cy, mdl.mirror_height_m, scale,
            4 * scale * max(mdl.width, mdl.height), gain, offset)
        rows = (int(rng.integers(0, _NOISE_SLACK_ROWS)), int(rng.integers(0, _NOISE_SLACK_ROWS)))
        scene = _Scene(lut, (lx, ly, theta - math.pi / 2),
                       Boxes(x, y, a, dims, body, top), body_px, top_px, [tuple(b) for b in bbox.tolist()], rows,
                       {}, lit.tolist(), has_top.tolist())
        return SyntheticFrame(self, scene)

    def render(
        self,
        leader_pose: FloatArray,
        followers_leader: FloatArray,
        t: float,
        rng: np.random.Generator,
        hidden: BoolArray | None = None,
    ) -> np.ndarray:
        """One whole BGR frame (H, W, 3) uint8 (arguments as for :meth:`frame`)."""
        return np.asarray(self.frame(leader_pose, followers_leader, t, rng, hidden))

    def _render_rect(self, scene: _Scene, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        """Rows y0..y1, columns x0..x1 of the scene's frame, exactly as in the whole frame.

        The blur needs one pixel around the rectangle, and OpenCV's anti-aliased polygons
        come out differently in the last rows before a clipping edge, so a margin of
        ``_RECT_MARGIN`` pixels is drawn too (inside the image: at the image's edges both the
        clipping and the blur's border rule are the whole frame's) and cut off."""
        s = self.settings
        h, w = self.shape[:2]
        m = _RECT_MARGIN
        ey0, ey1, ex0, ex1 = max(0, y0 - m), min(h, y1 + m), max(0, x0 - m), min(w, x1 + m)
        lx, ly, phi = scene.leader
        img = _background_rect(self._spans, self._row_spans, self._pa, self._pb, w, ey0, ey1, ex0, ex1, lx, ly, phi,
                               self._floor_tex, self._wall_tex, self._colours, _TEX_PPM, scene.lut)
        self._draw_boxes(img, scene, ex0, ey0, ex1, ey1)
        if s.blur_sigma_px > 0:
            img = cv2.GaussianBlur(img, (3, 3), s.blur_sigma_px)
        if (ey0, ey1, ex0, ex1) != (y0, y1, x0, x1):
            img = np.ascontiguousarray(img[y0 - ey0:y1 - ey0, x0 - ex0:x1 - ex0])
        if s.noise_sigma > 0:
            r0, r1 = scene.noise_rows
            cv2.add(img, self._noise_pos[r0 + y0:r0 + y1, x0:x1], dst=img)
            cv2.subtract(img, self._noise_neg[r1 + y0:r1 + y1, x0:x1], dst=img)
        return img

    def _draw_boxes(self, img: np.ndarray, scene: _Scene, x0: int, y0: int, x1: int, y1: int) -> None:
        """Draw, far to near, the boxes that reach into the rectangle ``img`` covers (its top
        left pixel is (x0, y0)): dark body silhouette, then the marker. Vertices move by whole
        pixels, so every pixel is drawn exactly as in the whole frame."""
        shift = None
        for i, (bx0, by0, bx1, by1) in enumerate(scene.bbox_list):
            if bx0 >= x1 or bx1 <= x0 or by0 >= y1 or by1 <= y0:
                continue
            look = scene.draw_cache.get(i)
            if look is None:
                look = scene.draw_cache[i] = self._box_look(scene, i)
            hull, body_colour, top, top_colour = look
            if shift is None:
                shift = np.array([x0 << _SUBPIXEL_BITS, y0 << _SUBPIXEL_BITS], np.int32)
            cv2.fillConvexPoly(img, hull - shift, body_colour, cv2.LINE_AA, _SUBPIXEL_BITS)
            if top is not None:
                cv2.fillPoly(img, [top - shift], top_colour, cv2.LINE_AA, _SUBPIXEL_BITS)

    @staticmethod
    def _box_look(scene: _Scene, i: int) -> tuple[np.ndarray, list[float], np.ndarray | None, list[float]]:
        """Box i's body outline (convex hull), lit body colour, marker outline (None: no
        marker) and lit marker colour, made when the box is first drawn."""
        lit = scene.lit_bgr[i]
        if scene.has_top[i]:
            return cv2.convexHull(scene.body_px[i]), lit[:3], scene.top_px[i], lit[3:]
        return cv2.convexHull(scene.body_px[i]), lit[:3], None, []
