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
from typing import Any

import cv2
import numpy as np

from core.camera.model import CameraModel
from core.camera.render.kernels import (ClutterAndTeam, Projection, background_into, background_rect, frame_layout,
                                        layout_boxes, pixel_tables, row_spans)
from core.camera.render.looks import Boxes, BoxLook, RenderSettings, look_dims, marker_bgr
from core.camera.render.textures import floor_texture, wall_texture
from core.geometry import pose_floats
from core.obstacles import Obstacle
from core.types import BoolArray, FloatArray

_TEX_PPM = 100.0  # floor texture: pixels per metre (1 cm texels)
_SUBPIXEL_BITS = 4  # polygon vertices with 1/16 pixel precision
_NOISE_SLACK_ROWS = 64
_RECT_MARGIN = 4  # pixels drawn around a rectangle of a frame and cut off (see Renderer._render_rect)


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


class Scratch:
    """Arrays a caller lends the renderer when it renders a rectangle of the same size again and
    again (the free-space scan's ring, every few frames), so that no such rendering allocates.

    Why: a process that gives every block over 64 KiB a mapping of its own (the service does,
    to keep a long run's memory bounded) gets each fresh block's pages from the system one
    fault at a time; for the scan's ring (three arrays of about 470 KiB) that took a scan from
    0.95 to 1.64 ms of CPU, a quarter of it in the kernel. What a rendering into a Scratch
    returns lives in its arrays: the caller's until its next use of the same Scratch."""

    def __init__(self) -> None:
        self._arrays: dict[str, np.ndarray] = {}

    def array(self, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """The uint8 array kept under ``name``, made anew only when ``shape`` changed (contents: whatever the last use left)."""
        a = self._arrays.get(name)
        if a is None or a.shape != shape:
            a = self._arrays[name] = np.empty(shape, np.uint8)
        return a


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

    def __array__(self, dtype: Any = None, /, *, copy: Any = None) -> np.ndarray:
        full: np.ndarray | None = self._full
        if full is None:
            h, w = self.shape[:2]
            full = self._renderer._render_rect(self._scene, 0, h, 0, w)
            self.pixels_rendered += h * w
            q = self._renderer.settings.jpeg_quality
            if q > 0:
                ok, buf = cv2.imencode(".jpg", full, [cv2.IMWRITE_JPEG_QUALITY, int(q)])
                if ok:
                    full = np.asarray(cv2.imdecode(buf, cv2.IMREAD_COLOR))
            self._full = full
        return full if dtype is None else full.astype(dtype)

    def __getitem__(self, key: object) -> np.ndarray:
        if type(key) is tuple and len(key) == 2 and type(key[0]) is slice and type(key[1]) is slice:
            rect = self._rect(key[0], key[1], None)
            if rect is not None:
                return rect
        return np.asarray(self)[key]  # type: ignore[call-overload]  # any numpy index, as for an array

    def region(self, rows: slice, cols: slice, scratch: Scratch) -> np.ndarray:
        """``self[rows, cols]`` (plain slices), rendered in ``scratch``'s arrays: the same pixels,
        valid until ``scratch`` is used again."""
        rect = self._rect(rows, cols, scratch)
        return rect if rect is not None else np.asarray(self)[rows, cols]

    def _rect(self, rows: slice, cols: slice, scratch: Scratch | None) -> np.ndarray | None:
        """The rectangle ``rows`` x ``cols`` made alone (in ``scratch``'s arrays when given); None
        where it cannot be: the whole frame made already, JPEG on (it mixes whole 8x8 blocks), a step."""
        if self._full is not None or rows.step not in (None, 1) or cols.step not in (None, 1) \
                or self._renderer.settings.jpeg_quality > 0:
            return None
        y0, y1, _ = rows.indices(self.shape[0])
        x0, x1, _ = cols.indices(self.shape[1])
        if y1 <= y0 or x1 <= x0:
            return np.empty((max(0, y1 - y0), max(0, x1 - x0), 3), np.uint8)
        self.pixels_rendered += (y1 - y0) * (x1 - x0)
        return self._renderer._render_rect(self._scene, y0, y1, x0, x1, scratch)


class Renderer:
    """Synthetic frames from one camera model; precomputes everything static at construction."""

    def __init__(self, model: CameraModel, settings: RenderSettings = RenderSettings(),
                 obstacles: tuple[Obstacle, ...] = ()) -> None:
        """``obstacles``: boxes fixed in the world (a scenario's), drawn where they stand."""
        self.model = model
        self.settings = settings
        h, w = model.height, model.width
        self.shape = (h, w, 3)
        kind, self._pa, self._pb = pixel_tables(
            model.to_mirror, model.xi, model.gamma_px, model.cx, model.cy, model.mirror_height_m,
            model.body_radius_px(), model.rim_radius_px(), settings.floor_far_m, h, w)
        self._spans, self._row_spans = row_spans(kind)
        tex_rng = np.random.default_rng(settings.texture_seed)
        self._floor_tex = floor_texture(tex_rng)
        self._wall_tex = wall_texture(tex_rng)
        self._colours = np.array([[6, 6, 6], [52, 50, 48]], np.uint8)  # beyond the rim; the leader's body
        # sensor noise: two non-negative banks (added, subtracted) with spare rows to shift
        sigma = settings.noise_sigma
        bank = tex_rng.standard_normal((h + _NOISE_SLACK_ROWS, w, 3), dtype=np.float32)
        bank *= np.float32(sigma)
        self._noise_pos = np.clip(bank, 0, 255).astype(np.uint8)
        np.negative(bank, out=bank)
        self._noise_neg = np.clip(bank, 0, 255).astype(np.uint8)
        self._clutter = self._make_clutter(tex_rng)
        # a NaN hue: a body without a marker (another team's leader, seen from a leader in a fleet)
        self._marker_colours = np.array([marker_bgr(hue, settings.marker_saturation, settings.marker_value)
                                         if math.isfinite(hue) else (math.nan, math.nan, math.nan)
                                         for hue in settings.hues_deg]).reshape(-1, 3)
        self._follower_dims = np.array(look_dims(settings.follower))
        self._follower_body = np.array([40.0, 40.0, 44.0])
        self.obstacles = tuple(obstacles)
        self._obstacles = self._make_obstacles(self.obstacles)

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
                             float(rng.uniform(-math.pi, math.pi)), look_dims(look), (grey, grey + 3, grey + 6), nan3))
        if s.distractor:
            look = BoxLook(0.12, 0.12, 0.12, 0.10, 0.10)
            rows.append((float(rng.uniform(0, s.clutter_period_m)), float(rng.uniform(0, s.clutter_period_m)),
                         0.0, look_dims(look), marker_bgr(s.distractor_hue_deg, 0.8, 0.7),
                         marker_bgr(s.distractor_hue_deg, 0.8, 0.8)))
        if not rows:
            return Boxes.empty()
        return Boxes(np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), np.array([r[2] for r in rows]),
                     np.array([r[3] for r in rows]), np.array([r[4] for r in rows]), np.array([r[5] for r in rows]))

    @staticmethod
    def _make_obstacles(obstacles: tuple[Obstacle, ...]) -> tuple[np.ndarray, ...]:
        """Obstacle boxes as ``layout_boxes`` takes them: cardboard browns, a little different each."""
        m = len(obstacles)
        body = np.array([[62.0 + 9 * (k % 3), 104.0 + 7 * (k % 2), 150.0 - 6 * (k % 4)] for k in range(m)]).reshape(m, 3)
        return (np.array([o.x for o in obstacles], dtype=np.float64), np.array([o.y for o in obstacles], dtype=np.float64),
                np.array([o.heading for o in obstacles], dtype=np.float64),
                np.array([(o.length, o.width, o.height, 0.0, 0.0) for o in obstacles], dtype=np.float64).reshape(m, 5),
                body)

    def boxes(self, leader_pose: FloatArray, followers_leader: FloatArray, hidden: BoolArray | None = None,
              clutter_only: bool = False) -> Boxes:
        """The frame's boxes in the leader frame, far to near: clutter within the floor's reach
        (none within 0.6 m of the leader or 0.45 m of a follower: the simulator has no
        collisions) and the followers' boxes, (n, 3) rows (x, y, a), not the hidden ones."""
        return Boxes(*layout_boxes(*self._layout_args(pose_floats(leader_pose), followers_leader, hidden,
                                                       clutter_only)))

    def _layout_args(self, leader: tuple[float, float, float], followers_leader: FloatArray,
                     hidden: BoolArray | None, clutter_only: bool = False) -> ClutterAndTeam:
        """The arguments of ``_layout_boxes`` for a frame; ``leader`` is its world pose (x, y, theta)."""
        cl = self._clutter
        fol = np.ascontiguousarray(np.asarray(followers_leader, dtype=np.float64).reshape(-1, 3))
        if clutter_only:
            visible = np.zeros(len(fol), dtype=np.bool_)
        elif hidden is None:
            visible = np.ones(len(fol), dtype=np.bool_)
        else:
            visible = ~np.asarray(hidden, dtype=np.bool_)[: len(fol)]
        return ClutterAndTeam(cl.x, cl.y, cl.a, cl.dims, cl.body_bgr, cl.top_bgr, fol, visible, self._follower_dims,
                              self._follower_body, self._marker_colours, *leader, self.settings.clutter_period_m,
                              self.settings.floor_far_m, *self._obstacles)

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
        projection = Projection(mdl.to_mirror, mdl.xi, mdl.gamma_px, mdl.cx, mdl.cy, mdl.mirror_height_m, scale,
                                4 * scale * max(mdl.width, mdl.height))
        f = frame_layout(layout, projection, gain, offset)
        rows = (int(rng.integers(0, _NOISE_SLACK_ROWS)), int(rng.integers(0, _NOISE_SLACK_ROWS)))
        scene = _Scene(f.lut, (lx, ly, theta - math.pi / 2),
                       Boxes(f.x, f.y, f.a, f.dims, f.body, f.top), f.body_px, f.top_px,
                       [tuple(b) for b in f.bbox.tolist()], rows, {}, f.lit.tolist(), f.has_top.tolist())
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

    def _render_rect(self, scene: _Scene, y0: int, y1: int, x0: int, x1: int,
                     scratch: Scratch | None = None) -> np.ndarray:
        """Rows y0..y1, columns x0..x1 of the scene's frame, exactly as in the whole frame; in
        ``scratch``'s arrays when given, else in new ones.

        The blur needs one pixel around the rectangle, and OpenCV's anti-aliased polygons
        come out differently in the last rows before a clipping edge, so a margin of
        ``_RECT_MARGIN`` pixels is drawn too (inside the image: at the image's edges both the
        clipping and the blur's border rule are the whole frame's) and cut off."""
        s = self.settings
        h, w = self.shape[:2]
        m = _RECT_MARGIN
        ey0, ey1, ex0, ex1 = max(0, y0 - m), min(h, y1 + m), max(0, x0 - m), min(w, x1 + m)
        lx, ly, phi = scene.leader
        tables = (self._spans, self._row_spans, self._pa, self._pb, w, ey0, ey1, ex0, ex1, lx, ly, phi,
                  self._floor_tex, self._wall_tex, self._colours, _TEX_PPM, scene.lut)
        if scratch is None:
            img = background_rect(*tables)
        else:
            flat = scratch.array("background", ((ey1 - ey0) * (ex1 - ex0) * 3,))
            background_into(flat, *tables)
            img = flat.reshape(ey1 - ey0, ex1 - ex0, 3)
        self._draw_boxes(img, scene, ex0, ey0, ex1, ey1)
        if s.blur_sigma_px > 0:
            blurred = None if scratch is None else scratch.array("blurred", img.shape)
            img = cv2.GaussianBlur(img, (3, 3), s.blur_sigma_px, dst=blurred)
        if (ey0, ey1, ex0, ex1) != (y0, y1, x0, x1):
            inner = img[y0 - ey0:y1 - ey0, x0 - ex0:x1 - ex0]
            if scratch is None:
                img = np.ascontiguousarray(inner)
            else:
                img = scratch.array("rectangle", inner.shape)
                np.copyto(img, inner)
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
