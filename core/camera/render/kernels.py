"""The renderer's compiled passes (numba): what every pixel shows, the background of a
rectangle, every box of a frame laid out and projected, and the frame's lighting."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from core.camera.render.textures import WALL_COLS, WALL_HEIGHT_M, WALL_ROWS
from core.jit import kernel

@kernel
def background_rect(
    spans: np.ndarray, row_spans: np.ndarray, pa: np.ndarray, pb: np.ndarray, width: int,
    y0: int, y1: int, x0: int, x1: int, leader_x: float, leader_y: float, phi: float,
    floor_tex: np.ndarray, wall_tex: np.ndarray, colours: np.ndarray, ppm: float, lut: np.ndarray,
) -> np.ndarray:
    """:func:`background_into` a new (y1 - y0, x1 - x0, 3) array."""
    out = np.empty((y1 - y0) * (x1 - x0) * 3, np.uint8)
    background_into(out, spans, row_spans, pa, pb, width, y0, y1, x0, x1, leader_x, leader_y, phi, floor_tex,
                    wall_tex, colours, ppm, lut)
    return out.reshape(y1 - y0, x1 - x0, 3)


@kernel
def background_into(
    out: np.ndarray, spans: np.ndarray, row_spans: np.ndarray, pa: np.ndarray, pb: np.ndarray, width: int,
    y0: int, y1: int, x0: int, x1: int, leader_x: float, leader_y: float, phi: float,
    floor_tex: np.ndarray, wall_tex: np.ndarray, colours: np.ndarray, ppm: float, lut: np.ndarray,
) -> None:
    """The pixels of rows y0..y1, columns x0..x1 before any box is drawn: floor texture under
    the leader's pose, distant walls, the leader's body, black beyond the mirror's rim.

    Each image row is a few runs of one kind of pixel: ``spans`` rows are (x_start, x_end,
    kind), those of image row y are ``spans[row_spans[y]:row_spans[y + 1]]``. Kinds: 0
    beyond the rim and 1 the leader's body (``colours`` rows, before lighting), 2 floor
    (pa, pb: where the pixel's ray meets the floor, leader frame, m), 3 wall (pa: azimuth in
    texture columns, pb: texture row); pa and pb are flat (row-major, ``width`` per row).
    The floor texture's side is a power of two, so wrapping is a bit mask; texel coordinates
    are kept positive so truncation is floor. Flat unsigned indices spare the compiled loop
    numpy's negative-index checks. ``out``: flat uint8, (y1 - y0) * (x1 - x0) * 3 of them, every
    one written (a caller may lend the same array again and again).
    """
    ow = x1 - x0
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


@kernel
def layout_boxes(
    cx: np.ndarray, cy: np.ndarray, ca: np.ndarray, cdims: np.ndarray, cbody: np.ndarray, ctop: np.ndarray,
    followers: np.ndarray, visible: np.ndarray, fdims: np.ndarray, fbody: np.ndarray, fcolours: np.ndarray,
    leader_x: float, leader_y: float, leader_theta: float, period: float, reach: float,
    ox: np.ndarray, oy: np.ndarray, oa: np.ndarray, odims: np.ndarray, obody: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every box of a frame in the leader frame, far to near (painter's order).

    Clutter: the world-fixed boxes of one cell (cx, cy world, m; ca world heading), the
    cell repeating every ``period`` metres; the instances of the 5 x 5 cells around the
    leader that lie between 0.6 m and ``reach`` - 0.3 m from it and at least 0.45 m from
    every follower (the simulator has no collisions, so a robot would drive into them).
    Followers: (x, y, a) leader frame, the visible ones, marker colour i mod len(fcolours).
    Obstacles: world-fixed boxes (ox, oy world, m; oa world heading), each once, within ``reach``.
    Returns x, y, a, dims (m, 5), body colour (m, 3), marker colour (m, 3; NaN: none).
    """
    phi = leader_theta - math.pi / 2
    c = math.cos(phi)
    s = math.sin(phi)
    n = followers.shape[0]
    k = cx.shape[0]
    cap = 25 * k + n + ox.shape[0]
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
    for q in range(ox.shape[0]):
        wx = ox[q] - leader_x
        wy = oy[q] - leader_y
        bx = c * wx + s * wy
        by = -s * wx + c * wy
        if math.hypot(bx, by) > reach + 0.5 * (odims[q, 0] + odims[q, 1]):
            continue
        x[m] = bx
        y[m] = by
        a[m] = oa[q] - phi
        dims[m] = odims[q]
        body[m] = obody[q]
        top[m] = math.nan
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
    cols_per_rad = WALL_COLS / (2.0 * math.pi)
    rows_per_m = WALL_ROWS / WALL_HEIGHT_M
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
            pb[i] = np.int32(min(max(wall_z * rows_per_m, 0.0), WALL_ROWS - 1.0))
    return kind, pa, pb


@kernel
def row_spans(kind: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
def box_polygons(
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
    ox: np.ndarray, oy: np.ndarray, oa: np.ndarray, odims: np.ndarray, obody: np.ndarray,
    to_mirror: np.ndarray, xi: float, gamma_px: float, ccx: float, ccy: float, mirror_height: float,
    scale: float, limit: float, gain: float, offset: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
           np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A frame's geometry and lighting in one call: the boxes (``layout_boxes``), their
    outlines and pixel bounds (``box_polygons``; bounds zero where a box does not project),
    their lit colours (m, 6: body then marker, clip(c * gain + offset, 0, 255)), whether
    each has a marker, and the lighting table for grey levels (the same clip, truncated)."""
    x, y, a, dims, body, top = layout_boxes(cx, cy, ca, cdims, cbody, ctop, followers, visible, fdims, fbody,
                                             fcolours, leader_x, leader_y, leader_theta, period, reach,
                                             ox, oy, oa, odims, obody)
    body_px, top_px, bbox, ok = box_polygons(x, y, a, dims, to_mirror, xi, gamma_px, ccx, ccy, mirror_height,
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




class ClutterAndTeam(NamedTuple):
    """What ``layout_boxes`` lays out for a frame: the clutter cell's boxes (world frame), the
    followers (leader frame) with their look, the leader's world pose, the cell period and the
    floor's reach (see ``layout_boxes``)."""

    cx: np.ndarray
    cy: np.ndarray
    ca: np.ndarray
    cdims: np.ndarray
    cbody: np.ndarray
    ctop: np.ndarray
    followers: np.ndarray
    visible: np.ndarray
    fdims: np.ndarray
    fbody: np.ndarray
    fcolours: np.ndarray
    leader_x: float
    leader_y: float
    leader_theta: float
    period: float
    reach: float
    ox: np.ndarray  # obstacles: world-fixed boxes, each drawn once (see layout_boxes)
    oy: np.ndarray
    oa: np.ndarray
    odims: np.ndarray
    obody: np.ndarray


class Projection(NamedTuple):
    """The camera model's projection, as ``box_polygons`` needs it, and the fixed-point scale
    and coordinate limit of the outlines."""

    to_mirror: np.ndarray
    xi: float
    gamma_px: float
    cx: float
    cy: float
    mirror_height: float
    scale: float
    limit: float


class FrameLayout(NamedTuple):
    """A frame's boxes far to near, their outlines, bounds and lit colours, and the lighting table."""

    x: np.ndarray
    y: np.ndarray
    a: np.ndarray
    dims: np.ndarray  # (m, 5)
    body: np.ndarray  # (m, 3) BGR before lighting
    top: np.ndarray  # (m, 3) BGR before lighting, NaN: no marker
    body_px: np.ndarray  # (m, 32, 2) int32 fixed point
    top_px: np.ndarray  # (m, 24, 2) int32 fixed point
    bbox: np.ndarray  # (m, 4) x0, y0, x1, y1; zero where the box does not project
    lit: np.ndarray  # (m, 6) lit body colour, then lit marker colour
    has_top: np.ndarray  # (m,) bool
    lut: np.ndarray  # (256,) uint8 lighting table


class PixelTables(NamedTuple):
    """What every pixel shows (see ``_pixel_tables``)."""

    kind: np.ndarray  # (H, W) uint8: 0 beyond the rim, 1 the leader's body, 2 floor, 3 wall
    pa: np.ndarray  # (H*W,) float32
    pb: np.ndarray  # (H*W,) float32


def frame_layout(layout: ClutterAndTeam, projection: Projection, gain: float, offset: float) -> FrameLayout:
    """A frame's geometry and lighting in one compiled call (``_frame_layout``)."""
    return FrameLayout(*_frame_layout(*layout, *projection, gain, offset))


def pixel_tables(to_mirror: np.ndarray, xi: float, gamma_px: float, cx: float, cy: float, mirror_height: float,
                 body_radius_px: float, rim_radius_px: float, floor_far: float, h: int, w: int) -> PixelTables:
    """What every pixel shows, from its view direction (``_pixel_tables``)."""
    return PixelTables(*_pixel_tables(to_mirror, xi, gamma_px, cx, cy, mirror_height, body_radius_px,
                                      rim_radius_px, floor_far, h, w))
