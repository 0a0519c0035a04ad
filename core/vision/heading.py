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

from core.geometry import reexpress_in_new_frame, wrap_angle
from core.types import FloatArray


def min_displacement(error_norm: FloatArray | float) -> FloatArray:
    """Eq. 34: Δs_min = 0.02 + 0.03 tanh(2 ‖P̃‖) (m)."""
    return 0.02 + 0.03 * np.tanh(2.0 * np.asarray(error_norm, dtype=np.float64))


def chord_headings(p1: FloatArray, p2: FloatArray, turns: FloatArray | float) -> FloatArray:
    """Eq. 35–37 for rows of points: heading at P₂ of an arc from P₁ that turned by
    ``turns`` (rad, CCW), not wrapped."""
    d = np.asarray(p2, dtype=np.float64) - np.asarray(p1, dtype=np.float64)
    return np.arctan2(d[..., 1], d[..., 0]) + 0.5 * np.asarray(turns, dtype=np.float64)


def chord_heading(p1: FloatArray, p2: FloatArray, turn: float) -> float:
    """Eq. 35–37: heading at P₂ of an arc from P₁ that turned by ``turn`` (rad, CCW)."""
    return float(wrap_angle(chord_headings(p1, p2, turn)))


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


class HeadingBank:
    """Every follower's heading: independent 1-D Kalman filters (filterpy's predict and
    update), held together so a frame costs one predict and one update for the whole team.

    The state is one heading per follower (rad); the covariance is diagonal (the filters
    do not interact). Residuals are taken on the circle. Only started filters move.
    """

    def __init__(self, n: int, process_rad_per_sqrt_s: float, measurement_rad: float) -> None:
        # imported by the first bank, not by every process that imports the pipeline (the page's,
        # a run on true poses): filterpy's package imports scipy.stats, over half a second of CPU
        from filterpy.kalman import predict, update

        self._kf_predict, self._kf_update = predict, update
        self.x = np.full(n, np.nan)
        self.var = np.zeros(n)
        self.active = np.zeros(n, dtype=bool)
        self._q = process_rad_per_sqrt_s**2
        self._r = measurement_rad**2
        self._rejected = np.zeros(n, dtype=np.int64)

    def start(self, i: int, a0: float, sigma0_rad: float) -> None:
        self.x[i] = float(wrap_angle(a0))
        self.var[i] = sigma0_rad**2
        self.active[i] = True
        self._rejected[i] = 0

    @property
    def headings(self) -> FloatArray:
        """Filtered headings (rad); NaN where not started."""
        return np.where(self.active, self.x, np.nan)

    @property
    def sigmas(self) -> FloatArray:
        return np.where(self.active, np.sqrt(self.var), np.nan)

    def predict(self, turns: FloatArray, dt: float) -> None:
        """Rotate each heading by its ``turns`` (rad): the follower's own commanded turn minus
        the leader's γ; the variance grows by the process noise over dt."""
        a = self.active
        if not a.any():
            return
        x, var = self._kf_predict(self.x[a], self.var[a], F=1.0, Q=self._q * dt, u=np.asarray(turns, dtype=np.float64)[a], B=1.0)
        self.x[a] = wrap_angle(x)
        self.var[a] = var

    def update(self, which: np.ndarray, measured: FloatArray, gate_sigmas: float = 4.0,
               max_rejections: int = 2) -> np.ndarray:
        """Fuse heading measurements ``measured`` of followers ``which`` (indices).

        A measurement further than ``gate_sigmas`` innovation sigmas from the prediction is
        rejected (a window disturbed by an occlusion gives a wild chord), unless it is the
        (max_rejections + 1)-th in a row: then the filter trusts the camera again.
        Returns, per measurement, whether it was fused.
        """
        idx = np.asarray(which, dtype=np.int64)
        z = np.asarray(measured, dtype=np.float64)
        residual = np.asarray(wrap_angle(z - self.x[idx]))
        s2 = self.var[idx] + self._r
        reject = (residual * residual > gate_sigmas * gate_sigmas * s2) & (self._rejected[idx] < max_rejections)
        self._rejected[idx[reject]] += 1
        ok = idx[~reject]
        self._rejected[ok] = 0
        m = len(ok)
        if m:
            eye = np.eye(m)
            x, cov = self._kf_update(self.x[ok].reshape(m, 1), np.diag(self.var[ok]),
                               (self.x[ok] + residual[~reject]).reshape(m, 1), self._r * eye, eye)
            self.x[ok] = wrap_angle(np.asarray(x).reshape(m))
            self.var[ok] = np.diag(cov)
        return ~reject


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


def arc_measurements(anchors: FloatArray, turns: FloatArray, travels: FloatArray, positions: FloatArray,
                     error_norms: FloatArray) -> FloatArray:
    """Eq. 34–37 for many followers at once: the heading measured at each position from its
    anchor (an ``ArcAnchor``'s point, turn and travel per row), NaN where the follower has
    not yet moved Δs_min (eq. 34) or a value is missing.

    A follower driving backwards moves against its heading: the chord is then turned by π.
    """
    d = np.asarray(positions, dtype=np.float64) - np.asarray(anchors, dtype=np.float64)
    far = np.hypot(d[:, 0], d[:, 1]) >= min_displacement(error_norms)
    a = chord_headings(anchors, positions, turns)
    a = np.where(np.asarray(travels) < 0, a + math.pi, a)
    out = np.full(a.shape, np.nan)
    far &= np.isfinite(a)
    out[far] = wrap_angle(a[far])
    return out


def arc_measurement(anchor: ArcAnchor, position: FloatArray, error_norm: float) -> float | None:
    """A heading measurement if the follower has moved far enough since the anchor (eq. 34), else None."""
    z = arc_measurements(anchor.point.reshape(1, 2), np.array([anchor.turn]), np.array([anchor.travel]),
                         np.asarray(position, dtype=np.float64).reshape(1, 2), np.array([error_norm]))[0]
    return None if math.isnan(z) else float(z)
