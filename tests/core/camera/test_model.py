"""The catadioptric camera model: projection and back projection, what the image shows."""

import math
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from core.camera.model import CameraModel, image_bearing


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
