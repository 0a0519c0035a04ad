"""How good a calibration is, before anyone relies on it: a held-out error, coverage
warnings, and the camera's turn and mirroring read from the table itself.

**Held-out error.** The fit's residuals at its own points say little about markers
elsewhere. Two refits tell more:

* leave one *interior* point out (not the nearest or farthest of its bearing, which would be
  an extrapolation no marker in the covered range needs): the error of the radial fit at a
  measured bearing;
* leave one *bearing* out: the error where Γ blends two sectors, but across twice the gap the
  full table has.

Blending error grows with the square of the gap between bearings, so leaving a bearing out
quadruples it; the estimate is e² = e_point² + max(0, e_bearing² − e_point²) / 16, for the
median and for the 95th percentile. A point left out of few errs more than a fresh marker
would: its bearing's range polynomial is a least-squares fit, where the left-out error of a
point of leverage h_k has variance σ²/(1 − h_k), and a fresh marker, measured as the table
was, σ²(1 + h̄) (h̄: the leverage averaged over the bearing's measured radii). Each left-out
error is scaled by sqrt((1 − h_k)(1 + h̄)), with the exact leverages of that polynomial. (The
rougher h ≈ p/n this replaced made the page's 6-a-bearing estimate 0.7 cm cautious on average
in the tail; six markers on a cubic leave interior leverages of 0.45–0.6, not 0.67.) On the
synthetic model (tilt 1–3°, centre 12 px off, 0.3 px of pixel noise) the estimate is within
1 cm of the error measured on 400 fresh markers everywhere in the covered ring, for 4, 6 and 8
bearings of 15 distances and for the page's 4 × 6 captures with 3 mm of placing error
(tests/core/camera/test_quality.py).

**Coverage.** Bearings more than 100° apart, and distances along a bearing more than 0.4 m
apart, leave places where positions are interpolated far from any marker: said plainly.

**Turn and mirror.** The bearing of each marker in the image against the bearing the table
states: for the right mirroring the difference is nearly the same for every marker (the
camera's turn); for the wrong one it spreads all round the circle. So the table says how the
camera is mounted, and a file written with that offset and flip is always one whose sector
corrections stay small (what ``locate`` and ``run`` accept).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.camera.gamma import RADIUS_UNIT_PX, CalibrationError, Gamma, MatchingTable, fit_gamma
from core.camera.model import bearing_range_to_xy, image_bearing

WARN_CM = 3.0  # positions off by more than this deserve a warning
BEARING_GAP_DEG = 100.0
DISTANCE_GAP_M = 0.4


def _subset(t: MatchingTable, keep: np.ndarray) -> MatchingTable:
    return MatchingTable(t.bearing_deg[keep], t.metres[keep], t.u[keep], t.v[keep])


def position_errors_cm(gamma: Gamma, t: MatchingTable) -> np.ndarray:
    """(N,) how far Γ puts each marker of ``t`` from where the table says it is, cm."""
    xy = bearing_range_to_xy(np.radians(t.bearing_deg), t.metres)
    return np.asarray(np.linalg.norm(gamma.pixel_to_leader(t.u, t.v) - xy, axis=1) * 100.0)


@dataclass(frozen=True)
class HeldOut:
    median_cm: float
    p95_cm: float
    point_p95_cm: float  # leave one interior point out
    bearing_p95_cm: float  # leave one bearing out (nan: fewer than 3 bearings)
    refits: int


def _fresh_scale(radii: np.ndarray, r_k: float, degree: int) -> float:
    """sqrt((1 - h_k)(1 + h̄)): a left-out error of the point at radius ``r_k`` of a bearing's
    range polynomial (over ``radii``, that point included) made a fresh marker's (module
    docstring)."""
    design = np.vander(radii, degree + 1)
    inv = np.linalg.pinv(design.T @ design)
    x_k = np.vander(np.array([r_k]), degree + 1)[0]
    h_k = float(x_k @ inv @ x_k)
    grid = np.vander(np.linspace(float(radii.min()), float(radii.max()), 64), degree + 1)
    h_bar = float(np.einsum("ij,jk,ik->i", grid, inv, grid).mean())
    return math.sqrt(max(0.0, 1.0 - h_k) * (1.0 + h_bar))


def held_out_error(table: MatchingTable, gamma: Gamma, degree: int) -> HeldOut:
    """The error to expect on markers the table does not have (see the module docstring)."""
    centre = (gamma.cx, gamma.cy)
    offset_deg = math.degrees(gamma.bearing_offset)
    point: list[float] = []
    refits = 0
    radius = np.hypot(table.u - gamma.cx, table.v - gamma.cy) / RADIUS_UNIT_PX
    for k in range(len(table)):
        line = np.round(table.bearing_deg, 6) == round(float(table.bearing_deg[k]), 6)
        d = table.metres[line]
        if table.metres[k] <= d.min() or table.metres[k] >= d.max() or line.sum() < degree + 3:
            continue
        keep = np.ones(len(table), dtype=bool)
        keep[k] = False
        try:
            g = fit_gamma(_subset(table, keep), center=centre, degree=degree, bearing_offset_deg=offset_deg,
                          flip=gamma.flip).gamma
        except CalibrationError:
            continue
        refits += 1
        point.extend(_fresh_scale(radius[line], radius[k], degree) * position_errors_cm(g, _subset(table, ~keep)))
    bearings = np.unique(np.round(table.bearing_deg, 6))
    by_bearing: list[float] = []
    if len(bearings) >= 3:
        for b in bearings:
            out = np.round(table.bearing_deg, 6) == b
            try:
                g = fit_gamma(_subset(table, ~out), center=centre, degree=degree, bearing_offset_deg=offset_deg,
                              flip=gamma.flip).gamma
            except CalibrationError:
                continue
            refits += 1
            by_bearing.extend(position_errors_cm(g, _subset(table, out)))
    if not point:  # too few points per bearing for an interior one: the residuals are all there is
        point = list(position_errors_cm(gamma, table))
    p = np.asarray(point)
    bb = np.asarray(by_bearing)

    def combined(q: float) -> float:
        a = float(np.percentile(p, q))
        if bb.size == 0:
            return a
        b = float(np.percentile(bb, q))
        return math.sqrt(a * a + max(0.0, b * b - a * a) / 16.0)

    return HeldOut(combined(50), combined(95), float(np.percentile(p, 95)),
                   float(np.percentile(bb, 95)) if bb.size else math.nan, refits)


def coverage_warnings(table: MatchingTable) -> list[str]:
    """Where the table leaves positions to be guessed far from any marker, one line each."""
    out: list[str] = []
    bearings = np.unique(np.round(table.bearing_deg % 360.0, 6))
    if len(bearings) == 1:
        out.append(f"one bearing only ({bearings[0]:g} deg): every other direction is a guess; measure at least 4")
    else:
        gaps = np.diff(np.concatenate([bearings, [bearings[0] + 360.0]]))
        for k in np.flatnonzero(gaps > BEARING_GAP_DEG):
            a, b = bearings[k], (bearings[k] + gaps[k]) % 360.0
            out.append(f"no bearing between {a:g} and {b:g} deg ({gaps[k]:g} deg): markers there are interpolated"
                       f" across the gap; add a bearing in it (at most {BEARING_GAP_DEG:g} deg apart)")
    for b in bearings:
        d = np.sort(table.metres[np.round(table.bearing_deg % 360.0, 6) == b])
        jumps = np.flatnonzero(np.diff(d) > DISTANCE_GAP_M)
        for k in jumps:
            out.append(f"bearing {b:g} deg: no marker between {d[k]:g} and {d[k + 1]:g} m; add some (at most"
                       f" {DISTANCE_GAP_M:g} m apart)")
    return out


@dataclass(frozen=True)
class Mounting:
    """How the camera is mounted, as the table shows it."""

    flip: bool
    offset_deg: float  # leader bearing that appears straight up, in (-180, 180]
    spread_deg: float  # how much the markers disagree about it (tilt and noise: a few degrees)
    other_spread_deg: float  # the same with the other mirroring (large when the table tells)

    @property
    def certain(self) -> bool:
        return self.spread_deg < 20.0 and self.other_spread_deg > 2.0 * self.spread_deg + 10.0


def _circular(angles: np.ndarray) -> tuple[float, float]:
    """(mean, spread) of angles in rad; spread = sqrt(-2 ln R), in rad."""
    c, s = float(np.mean(np.cos(angles))), float(np.mean(np.sin(angles)))
    r = min(1.0, math.hypot(c, s))
    return math.atan2(s, c), math.sqrt(-2.0 * math.log(max(r, 1e-12)))


def detect_mounting(table: MatchingTable, centre: tuple[float, float]) -> Mounting | None:
    """The camera's turn and mirroring from the table (None: too few bearings to tell)."""
    if len(np.unique(np.round(table.bearing_deg % 360.0, 6))) < 3:
        return None
    true_b = np.radians(table.bearing_deg)
    found = []
    for flip in (False, True):
        img = image_bearing(table.u, table.v, centre[0], centre[1], flip, 0.0)
        mean, spread = _circular(true_b - img)
        found.append((spread, flip, mean))
    found.sort()
    (spread, flip, mean), (other, _, _) = found
    offset = (math.degrees(mean) + 180.0) % 360.0 - 180.0
    return Mounting(flip, offset, math.degrees(spread), math.degrees(other))
