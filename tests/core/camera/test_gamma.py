"""Γ (paper §3): per-sector fits, blending across sectors, bad tables and fits refused."""

import math
import numpy as np
import pytest
from core.camera.gamma import CalibrationError, Gamma, MatchingTable, fit_gamma, parse_table
from core.camera.model import CameraModel, bearing_range_to_xy
from core.geometry import wrap_angle


def _exact_table(cam, bearings_deg, distances, height=0.102):
    rows = []
    for b in bearings_deg:
        for d in distances:
            xy = bearing_range_to_xy(math.radians(b), d)
            u, v = cam.project([[xy[0], xy[1], height]])[0]
            rows.append((b, d, u, v))
    a = np.array(rows)
    return MatchingTable(a[:, 0], a[:, 1], a[:, 2], a[:, 3])


def test_gamma_fits_an_exact_table_and_blends_smoothly_across_sectors():
    cam = CameraModel(tilt_deg=1.0, tilt_bearing_deg=30.0, flip=True, bearing_offset_deg=10.0)
    table = _exact_table(cam, range(0, 360, 45), np.arange(0.25, 1.8, 0.1))
    fit = fit_gamma(table, degree=5, flip=True, bearing_offset_deg=10.0)
    assert max(s.rms_cm for s in fit.sectors) < 0.3
    assert math.hypot(fit.gamma.cx - cam.cx, fit.gamma.cy - cam.cy) < 3.0
    # off the measured bearings, positions come out right too, and never jump
    b = np.radians(np.arange(0, 360, 0.25))
    for d in (0.4, 0.9, 1.4):
        xy = bearing_range_to_xy(b, np.full_like(b, d))
        px = cam.project(np.column_stack([xy, np.full(len(b), 0.102)]))
        got = fit.gamma.pixel_to_leader(px[:, 0], px[:, 1])
        err = np.linalg.norm(got - xy, axis=1)
        assert err.max() < 0.02, (d, err.max())
        steps = np.linalg.norm(np.diff(got, axis=0), axis=1)
        assert steps.max() < 2.5 * np.median(steps)


def test_gamma_blends_the_two_neighbouring_sectors_by_bearing():
    """Γ's rule, from known sectors: at a sector's centre its own polynomial and correction;
    between two centres (going round past ±180° too) the linear blend; NaN pixels give NaN;
    any shape of pixels keeps its shape."""
    g = Gamma(cx=320.0, cy=240.0, flip=False, bearing_offset=0.0,
              sector_bearings=np.radians([-120.0, 0.0, 120.0]),
              range_coeffs=np.array([[1.0, 0.1], [2.0, 0.2], [3.0, 0.3]]),  # metres = c0 + c1 (r / 100 px)
              bearing_corrections=np.radians([1.0, 2.0, 3.0]), r_min_px=0.0, r_max_px=300.0)
    r_px = 150.0
    cases = {  # image bearing (deg) -> (range m, correction deg)
        0.0: (2.0 + 0.2 * 1.5, 2.0),
        120.0: (3.0 + 0.3 * 1.5, 3.0),
        60.0: ((2.3 + 3.45) / 2, 2.5),
        -30.0: ((2.3 * 3 + 1.15) / 4, 1.75),
        180.0: ((3.45 + 1.15) / 2, 2.0),
    }
    for deg, (metres, corr) in cases.items():
        b = math.radians(deg)
        u, v = 320.0 - r_px * math.sin(b), 240.0 - r_px * math.cos(b)
        rng, bearing = g.range_bearing(np.array([u]), np.array([v]))
        assert rng[0] == pytest.approx(metres, abs=1e-12), deg
        assert math.degrees(float(wrap_angle(bearing[0] - b))) == pytest.approx(corr, abs=1e-9), deg
        np.testing.assert_allclose(g.pixel_to_leader(u, v), bearing_range_to_xy(b + math.radians(corr), metres), atol=1e-12)
    assert np.isnan(g.pixel_to_leader(np.array([np.nan, 300.0]), np.array([200.0, np.nan]))).all()
    assert g.pixel_to_leader(np.full((2, 3), 300.0), np.full((2, 3), 200.0)).shape == (2, 3, 2)


def test_gamma_uses_the_given_centre_and_sector_count():
    cam = CameraModel()
    table = _exact_table(cam, range(0, 360, 30), np.arange(0.3, 1.6, 0.1))
    fit = fit_gamma(table, center=(cam.cx, cam.cy), sectors=4)
    assert fit.gamma.n_sectors == 4 and not fit.center_estimated
    assert (fit.gamma.cx, fit.gamma.cy) == (cam.cx, cam.cy)
    assert all(s.points == 3 * 13 for s in fit.sectors)


@pytest.mark.parametrize(
    "text, message",
    [
        ("bearing_deg,metres,u\n0,1,2\n", "missing column 'v'; the header must be bearing_deg,metres,u,v"),
        ("bearing_deg,metres,u,v,w\n", "unknown column 'w'"),
        ("bearing_deg,metres,u,v\n0,nan,1,2\n", "line 2: metres = nan: must be a finite number"),
        ("bearing_deg,metres,u,v\n0,-1,1,2\n", "line 2: metres = -1: must not be negative"),
        ("bearing_deg,metres,u,v\n0,one,1,2\n", "line 2: metres = 'one' is not a number"),
        ("bearing_deg,metres,u,v\n0,1,2\n", "line 2 has 3 fields, the header has 4"),
        ("", "empty"),
    ],
)
def test_bad_tables_get_one_clear_line(text, message):
    with pytest.raises(CalibrationError) as err:
        parse_table(text, "t.csv")
    assert message in str(err.value) and "\n" not in str(err.value)


def test_bad_fits_are_refused():
    cam = CameraModel()
    table = _exact_table(cam, (0, 90, 180, 270), np.arange(0.3, 1.6, 0.3))  # 5 per sector
    with pytest.raises(CalibrationError, match="sector at -180 deg has 5 markers: a degree-4 fit needs at least 6"):
        fit_gamma(table, degree=4, center=(cam.cx, cam.cy))
    swapped = MatchingTable(table.bearing_deg, table.metres, table.u.copy(), table.v.copy())
    swapped.v[1], swapped.v[2] = swapped.v[2], swapped.v[1]  # bearing 0: the 0.6 m and 0.9 m pixels swapped
    with pytest.raises(CalibrationError, match="bearing 0 deg: radii and distances must increase together"):
        fit_gamma(swapped, degree=2, center=(cam.cx, cam.cy))
