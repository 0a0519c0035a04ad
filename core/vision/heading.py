"""Follower headings from positions alone (paper §3.2 and §3.3).

- The first heading a₀: the follower drives straight; its tracked positions are fitted
  with RANSAC (outliers out) then least squares; the line's direction, signed by the
  direction of motion, is a₀ (§3.2, fig. 11).
- While in formation: a new heading is measured only after the follower has moved
  Δs ≥ Δs_min = 0.02 + 0.03·tanh(2‖P̃‖) (eq. 34) from the last anchor point. Between
  measurements the anchor is re-expressed in the current leader frame with the leader's
  odometry (eq. 38, R(−γ) for a counter-clockwise γ, see core.geometry), and the heading
  estimate is rotated by −γ (a₁ = α₀ − γ) plus the follower's own commanded turn.
- Eq. 35–37 find the arc's centre O from the chord P₁P₂ and the turn ωΔt, and take the
  tangent at P₂. The tangent of a circular arc at its end makes half the arc's turn with
  the chord, so the same heading is atan2(P₂ − P₁) + ωΔt/2: identical to eq. 35–37 where
  those are defined, and well defined at ω = 0 (eq. 36 divides by tan(ωΔt/2)) and at
  x₂ = x₁ (the paper's special case).
- A Kalman filter (filterpy) on the heading, with residuals wrapped to (−π, π].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import KalmanFilter

from core.geometry import reexpress_in_new_frame, wrap_angle
from core.types import FloatArray


def min_displacement(error_norm: FloatArray | float) -> FloatArray:
    """Eq. 34: Δs_min = 0.02 + 0.03 tanh(2 ‖P̃‖) (m)."""
    return 0.02 + 0.03 * np.tanh(2.0 * np.asarray(error_norm, dtype=np.float64))


def chord_heading(p1: FloatArray, p2: FloatArray, turn: float) -> float:
    """Eq. 35–37: heading at P₂ of an arc from P₁ that turned by ``turn`` (rad, CCW)."""
    d = np.asarray(p2, dtype=np.float64) - np.asarray(p1, dtype=np.float64)
    return float(wrap_angle(math.atan2(float(d[1]), float(d[0])) + 0.5 * turn))


@dataclass(frozen=True)
class LineFit:
    heading: float  # rad, direction of motion
    inliers: np.ndarray  # bool mask
    rms_m: float  # perpendicular RMS of the inliers


def fit_heading_line(
    points: FloatArray, rng: np.random.Generator, iterations: int = 200, tolerance_m: float = 0.006,
) -> LineFit:
    """§3.2: RANSAC line through the points, least squares on its inliers, signed by motion.

    The sign: the direction in which the points progress in time (order of ``points``).
    """
    p = np.asarray(points, dtype=np.float64)
    m = p.shape[0]
    if m < 2:
        raise ValueError(f"a heading line needs at least 2 points, got {m}")
    best = np.ones(m, dtype=bool)
    best_count = -1
    if m > 2:
        for _ in range(iterations):
            i, j = rng.choice(m, 2, replace=False)
            d = p[j] - p[i]
            norm = math.hypot(float(d[0]), float(d[1]))
            if norm < 1e-9:
                continue
            normal = np.array([-d[1], d[0]]) / norm
            dist = np.abs((p - p[i]) @ normal)
            inl = dist < tolerance_m
            count = int(inl.sum())
            if count > best_count:
                best, best_count = inl, count
    q = p[best]
    centre = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - centre)
    direction = vt[0]
    # sign by the direction of motion: later points lie further along
    order = np.arange(m)[best]
    along = (q - centre) @ direction
    if len(order) > 1 and np.polyfit(order, along, 1)[0] < 0:
        direction = -direction
    perp = (q - centre) @ np.array([-direction[1], direction[0]])
    return LineFit(math.atan2(direction[1], direction[0]), best, float(np.sqrt(np.mean(perp**2))))


class HeadingFilter:
    """One follower's heading: a 1-D Kalman filter (filterpy) fed by eq. 34–37 measurements."""

    def __init__(self, a0: float, sigma0_rad: float, process_rad_per_sqrt_s: float, measurement_rad: float) -> None:
        kf = KalmanFilter(dim_x=1, dim_z=1, dim_u=1)
        kf.x = np.array([[a0]])
        kf.F = np.array([[1.0]])
        kf.B = np.array([[1.0]])
        kf.H = np.array([[1.0]])
        kf.P = np.array([[sigma0_rad**2]])
        kf.R = np.array([[measurement_rad**2]])
        self._kf = kf
        self._q = process_rad_per_sqrt_s**2
        self._rejected = 0

    @property
    def heading(self) -> float:
        return float(self._kf.x[0, 0])

    @property
    def sigma(self) -> float:
        return math.sqrt(float(self._kf.P[0, 0]))

    def predict(self, turn: float, dt: float) -> None:
        """Rotate by ``turn`` (rad): the follower's own commanded turn minus the leader's γ."""
        self._kf.Q = np.array([[self._q * dt]])
        self._kf.predict(u=np.array([[turn]]))
        self._kf.x[0, 0] = float(wrap_angle(self._kf.x[0, 0]))

    def update(self, measured: float, gate_sigmas: float = 4.0, max_rejections: int = 2) -> bool:
        """Fuse a heading measurement; the residual is taken on the circle.

        A measurement further than ``gate_sigmas`` innovation sigmas from the prediction is
        rejected (a window disturbed by an occlusion gives a wild chord), unless it is the
        (max_rejections + 1)-th in a row: then the filter trusts the camera again.
        Returns whether it was fused.
        """
        x = self.heading
        residual = float(wrap_angle(measured - x))
        s2 = float(self._kf.P[0, 0] + self._kf.R[0, 0])
        if residual * residual > gate_sigmas * gate_sigmas * s2 and self._rejected < max_rejections:
            self._rejected += 1
            return False
        self._rejected = 0
        self._kf.update(np.array([[x + residual]]))
        self._kf.x[0, 0] = float(wrap_angle(self._kf.x[0, 0]))
        return True


@dataclass
class ArcAnchor:
    """Where a follower was at its last heading measurement, in the current leader frame."""

    point: FloatArray  # (2,)
    turn: float = 0.0  # the follower's own turn since then (rad, from its commands)
    travel: float = 0.0  # signed distance it was commanded to drive since then (m)

    def move_leader(self, dx: float, dy: float, gamma: float) -> None:
        """Eq. 38: the leader moved by (dx, dy) (old frame) and turned by γ."""
        self.point = reexpress_in_new_frame(self.point, dx, dy, gamma)[0]

    def add_command(self, v: float, w: float, dt: float) -> None:
        self.turn += w * dt
        self.travel += v * dt


def arc_measurement(anchor: ArcAnchor, position: FloatArray, error_norm: float) -> float | None:
    """A heading measurement if the follower has moved far enough since the anchor (eq. 34), else None.

    A follower driving backwards moves against its heading: the chord is then turned by π.
    """
    d = np.asarray(position, dtype=np.float64) - anchor.point
    if math.hypot(float(d[0]), float(d[1])) < float(min_displacement(error_norm)):
        return None
    a = chord_heading(anchor.point, position, anchor.turn)
    if anchor.travel < 0:
        a = float(wrap_angle(a + math.pi))
    return a
