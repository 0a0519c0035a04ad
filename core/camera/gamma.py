"""Γ, the pixel -> metres transform of paper §3 (fig. 6), and its calibration fit.

The area around the leader is split into sectors, each with a matching table
(pixel distance from the image centre <-> metres on the floor) fitted by a polynomial
(``numpy.polynomial``). A real rig's mirror is slightly off-centre and tilted, so the
tables differ by sector, and so do the bearings: each sector also carries a bearing
correction. A pixel goes to (radius, image bearing) about the centre; its range and
bearing correction are blended linearly between the two neighbouring sectors' centres
(by bearing), so positions do not jump at sector borders; then range and bearing give
leader-frame (x, y).

Pure: text and arrays in, arrays out. Problems with a table raise
:class:`CalibrationError` whose message is one line naming what was wrong.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass

import numpy as np
from numpy.polynomial import polynomial as npoly

from core.camera.model import bearing_range_to_xy, image_bearing
from core.jit import kernel
from core.types import FloatArray

TABLE_COLUMNS = ("bearing_deg", "metres", "u", "v")
RADIUS_UNIT_PX = 100.0  # polynomials take radius / 100 px, so coefficients stay readable


class CalibrationError(ValueError):
    """A matching table or fit that cannot give a usable Γ: one line for people."""


@dataclass(frozen=True)
class MatchingTable:
    """Markers at known (bearing, distance) and the pixel where each marker's centre appears."""

    bearing_deg: FloatArray
    metres: FloatArray
    u: FloatArray
    v: FloatArray

    def __len__(self) -> int:
        return int(self.metres.shape[0])


def parse_table(text: str, source: str) -> MatchingTable:
    """Read TABLE.csv text with the header ``bearing_deg,metres,u,v`` (extra columns refused)."""
    reader = csv.reader(io.StringIO(text))
    rows = [r for r in reader if r and not (len(r) == 1 and not r[0].strip())]
    if not rows:
        raise CalibrationError(f"{source}: empty; expected the header {','.join(TABLE_COLUMNS)}")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in TABLE_COLUMNS if c not in header]
    if missing:
        raise CalibrationError(
            f"{source}: missing column {missing[0]!r}; the header must be {','.join(TABLE_COLUMNS)}"
        )
    extra = [h for h in header if h not in TABLE_COLUMNS]
    if extra:
        raise CalibrationError(f"{source}: unknown column {extra[0]!r}; allowed: {','.join(TABLE_COLUMNS)}")
    cols = {name: header.index(name) for name in TABLE_COLUMNS}
    values: dict[str, list[float]] = {name: [] for name in TABLE_COLUMNS}
    for line_no, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise CalibrationError(f"{source}: line {line_no} has {len(row)} fields, the header has {len(header)}")
        for name, idx in cols.items():
            text_value = row[idx].strip()
            try:
                value = float(text_value)
            except ValueError:
                raise CalibrationError(f"{source}: line {line_no}: {name} = {text_value!r} is not a number") from None
            if not math.isfinite(value):
                raise CalibrationError(f"{source}: line {line_no}: {name} = {text_value}: must be a finite number")
            if name != "bearing_deg" and value < 0:
                raise CalibrationError(f"{source}: line {line_no}: {name} = {text_value}: must not be negative")
            if name == "metres" and value == 0:
                raise CalibrationError(f"{source}: line {line_no}: metres = 0: a marker must be away from the leader")
            values[name].append(value)
    if len(values["metres"]) == 0:
        raise CalibrationError(f"{source}: no rows after the header")
    table = MatchingTable(*(np.array(values[c], dtype=np.float64) for c in TABLE_COLUMNS))
    repeated = repeated_rows(table)
    if repeated:
        raise CalibrationError(f"{source}: the same marker more than once: " + "; ".join(repeated))
    return table


DUPLICATE_PX = 3.0  # the same marker measured twice this close: a duplicate; farther: a contradiction


def repeated_rows(table: MatchingTable, first_line: int = 2) -> list[str]:
    """Every pair of rows that state the same (bearing, distance), by file line: a duplicate
    (the pixels agree) or a contradiction (they do not)."""
    out = []
    seen: dict[tuple[float, float], int] = {}
    for k in range(len(table)):
        key = (round(float(table.bearing_deg[k]) % 360.0, 6), round(float(table.metres[k]), 6))
        if key in seen:
            j = seen[key]
            gap = math.hypot(table.u[k] - table.u[j], table.v[k] - table.v[j])
            what = "a duplicate" if gap <= DUPLICATE_PX else "contradictory"
            out.append(f"lines {j + first_line} and {k + first_line} ({key[0]:g} deg, {key[1]:g} m) are {what},"
                       f" pixels {gap:.1f} px apart")
        else:
            seen[key] = k
    return out


@dataclass(frozen=True)
class Gamma:
    """The fitted transform. Angles in radians, radii in pixels."""

    cx: float
    cy: float
    flip: bool
    bearing_offset: float  # leader-frame bearing = image bearing + offset (+ correction)
    sector_bearings: FloatArray  # (k,) sector centres, image bearing, sorted, in [-pi, pi)
    range_coeffs: FloatArray  # (k, degree + 1): metres = sum c_i (r / 100 px)^i
    bearing_corrections: FloatArray  # (k,) rad, added to the bearing
    r_min_px: float  # calibrated radii (outside: extrapolated)
    r_max_px: float

    @property
    def n_sectors(self) -> int:
        return int(self.sector_bearings.shape[0])

    @property
    def degree(self) -> int:
        return int(self.range_coeffs.shape[1]) - 1

    def _apply(self, u: FloatArray, v: FloatArray) -> tuple[FloatArray, tuple[int, ...]]:
        """(N, 4) rows of range, bearing, x, y for the pixels (flattened), and their shape."""
        uu = np.asarray(u, dtype=np.float64)
        vv = np.asarray(v, dtype=np.float64)
        if uu.shape != vv.shape:
            uu, vv = np.broadcast_arrays(uu, vv)
        shape = uu.shape
        uu = np.ascontiguousarray(uu).reshape(-1)
        vv = np.ascontiguousarray(vv).reshape(-1)
        out = np.empty((uu.shape[0], 4))
        _gamma_kernel(uu, vv, self.cx, self.cy, self.flip, self.bearing_offset, self.sector_bearings,
                      self.range_coeffs, self.bearing_corrections, out)
        return out, shape

    def range_bearing(self, u: FloatArray, v: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Pixels -> (range m, corrected leader-frame bearing rad); NaN for NaN pixels."""
        out, shape = self._apply(u, v)
        return out[:, 0].reshape(shape), out[:, 1].reshape(shape)

    def pixel_to_leader(self, u: FloatArray, v: FloatArray) -> FloatArray:
        """Pixels -> leader-frame (x, y) in metres, shape (..., 2) (``bearing_range_to_xy``)."""
        out, shape = self._apply(u, v)
        return out[:, 2:].reshape(shape + (2,))


@kernel
def _gamma_kernel(u: FloatArray, v: FloatArray, cx: float, cy: float, flip: bool, offset: float,
                  centres: FloatArray, coeffs: FloatArray, corrections: FloatArray, out: FloatArray) -> None:
    """Γ per pixel: radius and image bearing about the centre (``image_bearing``); the two
    sectors whose centres enclose the bearing (sorted centres, going round) and the weight
    of the one after; each sector's range polynomial in radius / RADIUS_UNIT_PX (Horner);
    range and bearing correction blended linearly between them. Rows of ``out``: range,
    bearing, and the leader-frame (x, y) they give (``bearing_range_to_xy``)."""
    k = centres.shape[0]
    two_pi = 2.0 * math.pi
    c0 = centres[0]
    for n in range(u.shape[0]):
        du = u[n] - cx
        dv = v[n] - cy
        if not (math.isfinite(du) and math.isfinite(dv)):
            out[n, :] = math.nan
            continue
        radius = math.hypot(du, dv)
        if flip:
            du = -du
        b = math.atan2(-du, -dv) + offset
        i0 = 0
        i1 = 0
        w = 0.0
        if k > 1:
            rel = (b - c0) % two_pi  # from the first centre, in [0, 2 pi)
            after = 1  # the first centre whose position is beyond rel (rel >= the first's 0)
            while after < k and (centres[after] - c0) % two_pi <= rel:
                after += 1
            i0 = after - 1
            start = (centres[i0] - c0) % two_pi
            if after == k:
                span = two_pi - start
            else:
                i1 = after
                span = (centres[after] - c0) % two_pi - start
            w = (rel - start) / span
        x = radius / RADIUS_UNIT_PX
        r0 = 0.0
        r1 = 0.0
        for c in range(coeffs.shape[1] - 1, -1, -1):
            r0 = r0 * x + coeffs[i0, c]
            r1 = r1 * x + coeffs[i1, c]
        rng = (1.0 - w) * r0 + w * r1
        bearing = b + ((1.0 - w) * corrections[i0] + w * corrections[i1])
        out[n, 0] = rng
        out[n, 1] = bearing
        out[n, 2] = -rng * math.sin(bearing)
        out[n, 3] = rng * math.cos(bearing)


@dataclass(frozen=True)
class SectorFit:
    bearing_deg: float  # sector centre (leader frame, as in the table)
    points: int
    rms_cm: float
    max_cm: float
    bearing_correction_deg: float


@dataclass(frozen=True)
class GammaFit:
    gamma: Gamma
    sectors: tuple[SectorFit, ...]
    center_estimated: bool


def estimate_center(table: MatchingTable, start: tuple[float, float] | None = None) -> tuple[float, float]:
    """The image centre from the markers alone: the point about which a marker's pixel radius
    depends on its distance only (one common cubic R(d) for all bearings), by least squares."""
    uv = np.stack([table.u, table.v], axis=1)
    d = table.metres
    c0 = np.asarray(start if start is not None else uv.mean(axis=0), dtype=np.float64)
    scale = max(float(d.max()), 1e-9)
    basis = np.stack([(d / scale) ** i for i in range(4)], axis=1)

    def residual(params: FloatArray) -> FloatArray:
        r = np.hypot(uv[:, 0] - params[0], uv[:, 1] - params[1])
        return r - basis @ params[2:]

    r0 = np.hypot(uv[:, 0] - c0[0], uv[:, 1] - c0[1])
    coef0 = np.linalg.lstsq(basis, r0, rcond=None)[0]
    from scipy.optimize import least_squares  # here: scipy.optimize takes ~0.7 s to import, only fits need it

    sol = least_squares(residual, np.concatenate([c0, coef0]), method="lm")
    return float(sol.x[0]), float(sol.x[1])


def _wrap(a: FloatArray) -> FloatArray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def fit_gamma(
    table: MatchingTable,
    *,
    center: tuple[float, float] | None = None,
    sectors: int | None = None,
    degree: int = 3,
    bearing_offset_deg: float = 0.0,
    flip: bool = False,
    source: str = "table",
) -> GammaFit:
    """Fit Γ to a matching table (see ``omniformation calibrate``).

    Sectors are centred on the table's distinct bearings, or, with ``sectors=N``, on N
    evenly spaced bearings starting at the table's first bearing (each row joins the
    nearest). Without ``center`` the image centre is estimated from the data.
    """
    if degree < 1 or degree > 7:
        raise CalibrationError(f"degree = {degree}: must be from 1 to 7")
    if len(table) == 0:
        raise CalibrationError(f"{source}: no markers")
    estimated = center is None
    if center is None:
        if len(table) < 6:
            raise CalibrationError(f"{source}: {len(table)} markers cannot place the image centre; give --center CX CY or measure more")
        center = estimate_center(table)
    cx, cy = center
    offset = math.radians(bearing_offset_deg)
    true_b = np.radians(table.bearing_deg)
    img_b = image_bearing(table.u, table.v, cx, cy, flip, offset)
    radius = np.hypot(table.u - cx, table.v - cy)

    # sector centres, in the leader frame as the user stated them
    if sectors is None:
        uniq = np.unique(np.round(_wrap(true_b), 6))
        centres = np.sort(uniq)
    else:
        if sectors < 1 or sectors > 360:
            raise CalibrationError(f"sectors = {sectors}: must be from 1 to 360")
        first = float(_wrap(true_b[0]))
        centres = np.sort(_wrap(first + 2 * np.pi * np.arange(sectors) / sectors))
    member = np.argmin(np.abs(_wrap(true_b[:, None] - centres[None, :])), axis=1)

    coeffs = np.zeros((centres.shape[0], degree + 1))
    corrections = np.zeros(centres.shape[0])
    for j, c in enumerate(centres):
        sel = member == j
        n = int(sel.sum())
        name = f"{source}: sector at {math.degrees(c):g} deg"
        if n < degree + 2:
            raise CalibrationError(f"{name} has {n} markers: a degree-{degree} fit needs at least {degree + 2}")
        # along each measured bearing, a farther marker must appear farther out
        bearings_here = np.round(table.bearing_deg[sel], 6)
        for b_line in np.unique(bearings_here):
            on = bearings_here == b_line
            order = np.argsort(table.metres[sel][on], kind="stable")
            d_line = table.metres[sel][on][order]
            r_line = radius[sel][on][order]
            bad = (np.diff(d_line) <= 0) | (np.diff(r_line) <= 0)
            if np.any(bad):
                k = int(np.argmax(bad))
                raise CalibrationError(
                    f"{source}: bearing {b_line:g} deg: radii and distances must increase together, but"
                    f" {d_line[k]:g} m -> {r_line[k]:.1f} px and {d_line[k + 1]:g} m -> {r_line[k + 1]:.1f} px"
                )
        order = np.argsort(radius[sel])
        d_sorted = table.metres[sel][order]
        r_sorted = radius[sel][order]
        coeffs[j] = npoly.polyfit(r_sorted / RADIUS_UNIT_PX, d_sorted, degree)
        grid = np.linspace(r_sorted[0], r_sorted[-1], 64) / RADIUS_UNIT_PX
        if np.any(np.diff(npoly.polyval(grid, coeffs[j])) <= 0):
            raise CalibrationError(f"{name}: the degree-{degree} polynomial is not increasing over the measured radii; use a lower --degree")
        err = _wrap(true_b[sel] - img_b[sel])
        corrections[j] = float(np.arctan2(np.sin(err).mean(), np.cos(err).mean()))

    # The sectors are indexed by where they appear in the image: image bearing = true - correction.
    sector_img = _wrap(centres - corrections)
    order = np.argsort(sector_img)
    gamma = Gamma(
        cx=float(cx), cy=float(cy), flip=bool(flip), bearing_offset=offset,
        sector_bearings=sector_img[order], range_coeffs=coeffs[order], bearing_corrections=corrections[order],
        r_min_px=float(radius.min()), r_max_px=float(radius.max()),
    )
    # residuals of the whole transform (blending included), per sector, in cm
    xy_true = bearing_range_to_xy(true_b, table.metres)
    xy_fit = gamma.pixel_to_leader(table.u, table.v)
    err_cm = np.linalg.norm(xy_fit - xy_true, axis=1) * 100.0
    fits = []
    for j, c in enumerate(centres):
        e = err_cm[member == j]
        fits.append(SectorFit(math.degrees(c), int(e.shape[0]), float(np.sqrt(np.mean(e**2))), float(e.max()),
                              math.degrees(corrections[j])))
    return GammaFit(gamma, tuple(fits), estimated)
