"""The leader's central catadioptric camera: the unified sphere model, with a real rig's flaws.

Frames
------
Leader frame (as everywhere in this project): x to the leader's right, y forward, z up,
origin on the floor under the mirror axis. The mirror's single viewpoint is at height
``mirror_height_m``.

Unified sphere model (Geyer & Daniilidis; Mei & Rives): a 3-D point X seen from the
viewpoint is put on the unit sphere, Xs = X/|X|, shifted by the mirror parameter ξ along
the mirror axis and projected: m = (xs, ys)/(zs + ξ); pixel = γ·m + (cx, cy).
ξ = 1 is a parabolic mirror, 0 < ξ < 1 a hyperbolic one (paper §3: hyperbolic).

Mirror frame: z_m points down the mirror axis (towards the floor), x_m along image +u,
y_m along image +v. With no flaws, image up (−v) is the leader's forward (+y) and image
right (+u) the leader's right (+x): the picture reads like a top-down view.

Flaws of a real rig, all in :class:`CameraModel`:
- the principal point (cx, cy) off the image centre by a few pixels (the mirror axis);
- the mirror axis tilted by ``tilt_deg`` towards leader-frame bearing ``tilt_bearing_deg``;
- a bearing offset: leader-frame bearing β appears at image bearing β − offset;
- a mirror flip: the image is mirrored left/right.

Bearings: 0 straight ahead (+y), positive counter-clockwise seen from above (towards −x).
In the image (no flip, no offset) bearing 0 is straight up and positive turns towards the left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from core.types import FloatArray


def _rot_x(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics, mounting and flaws. Angles in degrees as a person states them."""

    width: int = 640
    height: int = 480
    xi: float = 0.8  # mirror parameter
    gamma_px: float = 188.0  # generalised focal length (pixels)
    cx: float = 324.0
    cy: float = 237.0
    mirror_height_m: float = 0.55  # single viewpoint above the floor
    tilt_deg: float = 1.0
    tilt_bearing_deg: float = 30.0
    bearing_offset_deg: float = 0.0
    flip: bool = False
    rim_elevation_deg: float = 2.0  # the mirror sees up to this far above the horizon
    body_radius_m: float = 0.25  # the leader's own body hides the floor within this radius

    # derived, not part of the constructor
    to_mirror: FloatArray = field(init=False, repr=False, compare=False)  # (3, 3) camera axes -> mirror axes

    def __post_init__(self) -> None:
        # leader-frame direction -> mirror-frame direction.
        # 1. undo the tilt (rotate about the axis perpendicular to the tilt bearing),
        tb = math.radians(self.tilt_bearing_deg)
        tilt = _rot_z(tb) @ _rot_x(math.radians(self.tilt_deg)) @ _rot_z(-tb)
        # 2. the bearing offset turns the picture: bearing beta appears at beta - offset,
        turn = _rot_z(-math.radians(self.bearing_offset_deg))
        # 3. axes: x_m = x, y_m = -y (forward is image up), z_m = -z (the axis looks down),
        axes = np.diag([1.0, -1.0, -1.0])
        # 4. the flip mirrors the image left/right.
        flip = np.diag([-1.0 if self.flip else 1.0, 1.0, 1.0])
        object.__setattr__(self, "to_mirror", flip @ axes @ turn @ tilt.T)

    def replace(self, **changes: Any) -> "CameraModel":
        return replace(self, **changes)

    @property
    def center(self) -> tuple[float, float]:
        return (self.cx, self.cy)

    def horizon_radius_px(self) -> float:
        """Image radius of the horizon (zs = 0) for an untilted mirror: γ/ξ."""
        return self.gamma_px / self.xi

    def rim_radius_px(self) -> float:
        """Image radius of the mirror's outer rim (what lies beyond is black)."""
        e = math.radians(self.rim_elevation_deg)
        return self.gamma_px * math.cos(e) / (self.xi - math.sin(e))

    # -- projection ----------------------------------------------------------------------

    def directions_to_pixels(self, d: FloatArray) -> FloatArray:
        """Leader-frame view directions (…, 3) (any length) -> pixels (…, 2) [u, v]."""
        d = np.asarray(d, dtype=np.float64)
        m = d @ self.to_mirror.T
        n = np.linalg.norm(m, axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            denom = m[..., 2] + self.xi * n
            u = self.gamma_px * m[..., 0] / denom + self.cx
            v = self.gamma_px * m[..., 1] / denom + self.cy
        return np.stack([u, v], axis=-1)

    def project(self, points: FloatArray) -> FloatArray:
        """Leader-frame 3-D points (…, 3) in metres -> pixels (…, 2)."""
        p = np.asarray(points, dtype=np.float64)
        d = p - np.array([0.0, 0.0, self.mirror_height_m])
        return self.directions_to_pixels(d)

    def pixels_to_directions(self, pixels: FloatArray) -> FloatArray:
        """Pixels (…, 2) -> unit view directions (…, 3) in the leader frame (inverse of projection)."""
        px = np.asarray(pixels, dtype=np.float64)
        mx = (px[..., 0] - self.cx) / self.gamma_px
        my = (px[..., 1] - self.cy) / self.gamma_px
        r2 = mx * mx + my * my
        xi = self.xi
        eta = (xi + np.sqrt(1.0 + (1.0 - xi * xi) * r2)) / (r2 + 1.0)
        m = np.stack([eta * mx, eta * my, eta - xi], axis=-1)
        return m @ self.to_mirror  # orthonormal: inverse = transpose

    def pixels_to_floor(self, pixels: FloatArray, height_m: float = 0.0) -> FloatArray:
        """Pixels (…, 2) -> leader-frame (x, y) where their rays meet the plane z = height_m.

        Rays that never reach the plane (at or above the horizon) give NaN.
        """
        d = self.pixels_to_directions(pixels)
        drop = height_m - self.mirror_height_m
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(d[..., 2] < -1e-9, drop / d[..., 2], np.nan)
        return np.stack([t * d[..., 0], t * d[..., 1]], axis=-1)

    def floor_radius_px(self, distance_m: float, height_m: float = 0.0) -> float:
        """Image radius (from the principal point) of a point at a range, flaws ignored."""
        drop = self.mirror_height_m - height_m
        return self.gamma_px * distance_m / (drop + self.xi * math.hypot(distance_m, drop))

    def body_radius_px(self) -> float:
        """Image radius inside which the leader's own body hides the floor."""
        return self.floor_radius_px(self.body_radius_m)


def image_bearing(u: FloatArray, v: FloatArray, cx: float, cy: float, flip: bool, offset_rad: float) -> FloatArray:
    """Leader-frame bearing (rad) of pixels seen from a centre, given flip and bearing offset.

    The inverse of the orientation convention above (tilt not included: Γ corrects that).
    """
    du = np.asarray(u, dtype=np.float64) - cx
    dv = np.asarray(v, dtype=np.float64) - cy
    if flip:
        du = -du
    return np.arctan2(-du, -dv) + offset_rad


def bearing_range_to_xy(bearing: FloatArray, range_m: FloatArray) -> FloatArray:
    """Leader-frame (x, y) of a bearing (0 ahead, CCW positive) and a range."""
    b = np.asarray(bearing, dtype=np.float64)
    r = np.asarray(range_m, dtype=np.float64)
    return np.stack([-r * np.sin(b), r * np.cos(b)], axis=-1)


def xy_to_bearing_range(xy: FloatArray) -> tuple[FloatArray, FloatArray]:
    p = np.asarray(xy, dtype=np.float64)
    return np.arctan2(-p[..., 0], p[..., 1]), np.hypot(p[..., 0], p[..., 1])
