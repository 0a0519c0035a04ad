"""The catadioptric model, the synthetic renderer and Γ, on real OpenCV images."""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.camera.config import WorkingArea, parse_camera
from core.camera.gamma import CalibrationError, Gamma, MatchingTable, fit_gamma, parse_table
from core.camera.model import CameraModel, bearing_range_to_xy, image_bearing
from core.camera.render import Renderer, RenderSettings
from core.config import ConfigError
from core.geometry import wrap_angle
from core.vision.blobs import DetectSettings, find_blobs, hue_distance_deg

SYNTHETIC = "static_config/camera/synthetic.toml"


@pytest.fixture(scope="module")
def camera_config():
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    return parse_camera((root / SYNTHETIC).read_text(), SYNTHETIC)


RIGS = [
    CameraModel(),
    CameraModel(flip=True, bearing_offset_deg=25.0),
    CameraModel(tilt_deg=2.0, tilt_bearing_deg=-70.0, cx=310.0, cy=250.0, xi=0.95),
]


@pytest.mark.parametrize("cam", RIGS)
@settings(max_examples=40, deadline=None)
@given(xs=st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.0, 0.3)), min_size=1, max_size=20))
def test_projection_and_back_projection_invert_each_other(cam, xs):
    p = np.array(xs)
    p = p[np.hypot(p[:, 0], p[:, 1]) > 0.05]
    if len(p) == 0:
        return
    px = cam.project(p)
    back = cam.pixels_to_floor(px, height_m=p[:, 2])
    np.testing.assert_allclose(back, p[:, :2], atol=1e-9)
    # and rays: pixels -> directions -> pixels
    d = cam.pixels_to_directions(px)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cam.directions_to_pixels(d), px, atol=1e-9)


def test_image_reads_like_a_top_down_view():
    cam = CameraModel(tilt_deg=0.0, cx=320.0, cy=240.0)
    ahead, right, left = cam.project([[0, 1, 0], [1, 0, 0], [-1, 0, 0]])
    assert ahead[1] < 240 and abs(ahead[0] - 320) < 1e-9  # forward is image up
    assert right[0] > 320 and abs(right[1] - 240) < 1e-9  # right is image right
    assert left[0] < 320
    flipped = cam.replace(flip=True).project([[1, 0, 0]])[0]
    assert flipped[0] < 320  # flip mirrors left/right
    turned = cam.replace(bearing_offset_deg=30.0)
    b = math.radians(30.0)
    up = turned.project([[-math.sin(b), math.cos(b), 0.0]])[0]  # bearing 30 deg (CCW) appears straight up
    assert abs(up[0] - 320) < 1e-9 and up[1] < 240
    # image_bearing inverts the convention
    for c in (cam, cam.replace(flip=True), turned):
        for bearing in (-2.0, -0.5, 0.3, 1.7):
            px = c.project([[-math.sin(bearing), math.cos(bearing), 0.0]])[0]
            got = image_bearing(px[0], px[1], c.cx, c.cy, c.flip, math.radians(c.bearing_offset_deg))
            assert math.isclose(math.remainder(float(got) - bearing, 2 * math.pi), 0.0, abs_tol=1e-9)


def test_radius_grows_with_distance_and_the_body_hides_the_centre():
    cam = CameraModel()
    radii = [cam.floor_radius_px(d, 0.1) for d in np.linspace(0.1, 5, 50)]
    assert np.all(np.diff(radii) > 0) and radii[-1] < cam.horizon_radius_px()
    assert cam.body_radius_px() < cam.floor_radius_px(0.3, 0.1) < cam.floor_radius_px(1.5, 0.1) < cam.rim_radius_px()


def test_config_file_parses_and_bad_values_are_named(camera_config):
    assert camera_config.model is not None and camera_config.model.tilt_deg == 1.0
    assert camera_config.working_area == WorkingArea(55.0, 195.0)
    text = "[working_area]\ninner_px = 80\nouter_px = 60\n"
    with pytest.raises(ConfigError, match=r"cam.toml: working_area.outer_px = 60.0: must be > inner_px \(80\)"):
        parse_camera(text, "cam.toml")
    with pytest.raises(ConfigError, match=r"model.xi = 1.5: must be a number in \(0, 1\]"):
        parse_camera("[working_area]\ninner_px=1\nouter_px=2\n[model]\nwidth=640\nheight=480\nxi=1.5\n", "cam.toml")
    with pytest.raises(ConfigError, match="render.sparkle is not a known key"):
        parse_camera("[working_area]\ninner_px=1\nouter_px=2\n[render]\nsparkle=1\n", "cam.toml")


# ---------------------------------------------------------------- renderer


def _hue_pixels(img, hue_deg, tol=12):
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    h = hsv[..., 0].astype(float) * 2
    d = np.minimum(np.abs(h - hue_deg), 360 - np.abs(h - hue_deg))
    return (d < tol) & (hsv[..., 1] > 90) & (hsv[..., 2] > 50)


def test_render_draws_each_marker_where_the_model_projects_it(camera_config):
    cam = camera_config.model
    r = Renderer(cam, RenderSettings(clutter=False, distractor=False))
    followers = np.array([[-0.6, 0.4, 0.3], [0.8, -0.2, 2.0], [0.1, -1.2, -1.0]])
    img = r.render(np.array([1.0, 2.0, 0.4]), followers, 3.0, np.random.default_rng(0))
    assert img.shape == (480, 640, 3) and img.dtype == np.uint8
    for i, (x, y, _) in enumerate(followers):
        mask = _hue_pixels(img, r.settings.hues_deg[i])
        assert mask.sum() > 30
        vv, uu = np.nonzero(mask)
        expected = cam.project([[x, y, 0.102]])[0]
        assert math.hypot(uu.mean() - expected[0], vv.mean() - expected[1]) < 2.0
    # beyond the mirror's rim the image is (nearly) black, the leader's body dark
    assert img[2, 2].max() < 30
    centre = img[int(cam.cy), int(cam.cx)]
    assert centre.max() < 90


def test_render_is_deterministic_and_hidden_followers_vanish(camera_config):
    r = Renderer(camera_config.model, camera_config.render)
    f = np.array([[-0.6, 0.4, 0.3], [0.8, -0.2, 2.0]])
    pose = np.array([0.3, -0.2, 1.0])
    a = r.render(pose, f, 5.0, np.random.default_rng(3))
    b = r.render(pose, f, 5.0, np.random.default_rng(3))
    assert np.array_equal(a, b)
    c = r.render(pose, f, 5.0, np.random.default_rng(3), hidden=np.array([True, False]))
    assert _hue_pixels(c, r.settings.hues_deg[0]).sum() == 0
    assert _hue_pixels(c, r.settings.hues_deg[1]).sum() > 30
    # the floor moves under a moving leader; lighting drifts with time
    moved = r.render(pose + [0.05, 0.0, 0.0], f, 5.0, np.random.default_rng(3))
    assert np.abs(moved.astype(int) - a.astype(int)).mean() > 1.0
    period = r.settings.drift_period_s
    bright = r.render(pose, f, period / 4, np.random.default_rng(3))
    dim = r.render(pose, f, 3 * period / 4, np.random.default_rng(3))
    assert r.lighting(period / 4)[0] > 1.1 > 0.9 > r.lighting(3 * period / 4)[0]
    assert bright.mean() > dim.mean() + 8


def test_jpeg_round_trip_is_applied_when_asked(camera_config):
    base = camera_config.render
    f = np.array([[-0.6, 0.4, 0.3]])
    raw = Renderer(camera_config.model, base).render(np.zeros(3), f, 0.0, np.random.default_rng(1))
    jpg = Renderer(camera_config.model, RenderSettings(**{**base.__dict__, "jpeg_quality": 30})).render(
        np.zeros(3), f, 0.0, np.random.default_rng(1))
    assert 0.5 < np.abs(raw.astype(int) - jpg.astype(int)).mean() < 10


# ---------------------------------------------------------------- Γ


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


# ---------------------------------------------------------------- blobs


def test_blobs_merge_same_colour_pieces_and_ignore_grey():
    img = np.full((200, 200, 3), 128, np.uint8)
    cv2.rectangle(img, (40, 40), (60, 50), (0, 0, 220), -1)
    cv2.rectangle(img, (40, 54), (60, 64), (0, 0, 220), -1)  # the same rectangle, cut by a reflection
    cv2.rectangle(img, (120, 120), (140, 150), (0, 200, 0), -1)
    cv2.rectangle(img, (10, 150), (60, 190), (90, 95, 100), -1)  # grey box
    blobs = find_blobs(img, None, DetectSettings())
    assert len(blobs) == 2
    red = min(blobs, key=lambda b: hue_distance_deg(b.hue_deg, 0.0))
    assert hue_distance_deg(red.hue_deg, 0.0) < 3 and red.area_px == 2 * 21 * 11
    assert abs(red.v - 52.0) < 0.6 and abs(red.u - 50.0) < 1e-9


def test_a_frame_rendered_by_rectangles_is_the_whole_frame_bit_for_bit(camera_config):
    """SyntheticFrame makes only the rectangles looked at, and each is exactly the whole
    frame's pixels there: boxes cut by the rectangle's edge, the blur's neighbours, noise."""
    r = Renderer(camera_config.model, camera_config.render)
    rng = np.random.default_rng(8)
    followers = np.array([[-0.6, 0.4, 0.3], [0.8, -0.2, 2.0], [0.1, -1.2, -1.0], [0.3, 0.5, 1.1]])
    for k in range(6):
        pose = np.array([0.4 * k, -0.3 * k, 0.7 * k])
        whole = r.render(pose, followers, 2.0 * k, np.random.default_rng(k))
        lazy = r.frame(pose, followers, 2.0 * k, np.random.default_rng(k))
        h, w = whole.shape[:2]
        # around each follower (where CAMSHIFT looks), plus random ones, plus the image's edges
        u, v = camera_config.model.project(np.column_stack([followers[:, :2], np.full(len(followers), 0.1)])).T
        rects = [(int(vv) - 20, int(vv) + 17, int(uu) - 23, int(uu) + 19) for uu, vv in zip(u, v)]
        for _ in range(40):
            y0, x0 = int(rng.integers(-5, h)), int(rng.integers(-5, w))
            rects.append((y0, y0 + int(rng.integers(1, 90)), x0, x0 + int(rng.integers(1, 90))))
        rects += [(0, 9, 0, w), (h - 7, h, 0, 33), (0, h, w - 3, w)]
        for y0, y1, x0, x1 in rects:
            y0, x0 = max(0, y0), max(0, x0)
            assert np.array_equal(lazy[y0:y1, x0:x1], whole[y0:y1, x0:x1]), (k, y0, y1, x0, x1)
        assert lazy.pixels_rendered < h * w  # only the rectangles were made
        assert np.array_equal(np.asarray(lazy), whole)
        assert np.array_equal(lazy[5:9, 7:600:3], whole[5:9, 7:600:3])  # any other index: the whole frame's
