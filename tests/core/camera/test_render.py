"""The synthetic renderer on real OpenCV images: markers where the model projects them, determinism, JPEG, rectangles."""

import math
import cv2
import numpy as np
from core.camera.render import Renderer, RenderSettings
from core.camera.render.renderer import Scratch


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
        # into arrays lent again and again (the scan's ring): the same pixels, whatever the last use left there
        lent, scratch = r.frame(pose, followers, 2.0 * k, np.random.default_rng(k)), Scratch()
        for y0, y1, x0, x1 in rects[:12] + [(0, h, 0, w)] + rects[:12]:
            y0, x0 = max(0, y0), max(0, x0)
            assert np.array_equal(lent.region(slice(y0, y1), slice(x0, x1), scratch), whole[y0:y1, x0:x1]), (k, y0, x0)
        assert np.array_equal(np.asarray(lazy), whole)
        assert np.array_equal(lazy[5:9, 7:600:3], whole[5:9, 7:600:3])  # any other index: the whole frame's
