"""CAMSHIFT's input: the one-pass back projection is OpenCV's, colour for colour."""

import cv2
import numpy as np
from core.camera.config import DetectSettings
from core.camera.render import Renderer
from core.vision.tracking import back_projection, hue_histogram, hue_lookup


def every_colour() -> np.ndarray:
    """A 4096 x 4096 BGR image holding each of the 2^24 colours once."""
    c = np.arange(1 << 24, dtype=np.uint32).reshape(4096, 4096)
    return np.dstack([c & 255, (c >> 8) & 255, c >> 16]).astype(np.uint8)


def test_the_one_pass_back_projection_is_opencvs_hsv_on_every_colour():
    img = every_colour()
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    everywhere = np.full(img.shape[:2], 255, np.uint8)
    # a lookup that is the identity shows the hue byte itself
    hue = back_projection(img, np.arange(256, dtype=np.uint8), everywhere, DetectSettings(min_saturation=0, min_value=0))
    assert np.array_equal(hue, hsv[..., 0])
    # a lookup of all 255 shows which pixels pass the saturation and value floors
    for s_min, v_min in ((90, 50), (1, 0), (0, 255), (255, 1), (37, 201)):
        passed = back_projection(img, np.full(256, 255, np.uint8), everywhere,
                                 DetectSettings(min_saturation=s_min, min_value=v_min))
        assert np.array_equal(passed, cv2.inRange(hsv, (0, s_min, v_min), (180, 255, 255))), (s_min, v_min)


def test_the_one_pass_back_projection_is_the_opencv_chain_on_a_rendered_frame(rig):
    frame = Renderer(rig.model, rig.render).render(np.zeros(3), np.array([[0.0, 0.6, 1.0], [-0.5, 0.4, 2.0]]), 0.0,
                                                   np.random.default_rng(3))
    hsv = cv2.cvtColor(frame, cv2.COLOR_BGR2HSV)
    detect = rig.detect
    sat = cv2.inRange(hsv, (0, detect.min_saturation, detect.min_value), (180, 255, 255))
    area = np.zeros(frame.shape[:2], np.uint8)
    cv2.circle(area, (320, 240), 200, 255, -1)
    hist = hue_histogram(hsv, sat)
    chain = cv2.bitwise_and(cv2.bitwise_and(cv2.calcBackProject([hsv], [0], hist, [0, 180], 1), sat), area)
    assert chain.any()
    assert np.array_equal(back_projection(frame, hue_lookup(hist), area, detect), chain)
    # a region of the frame (a strided view, as a camera frame's ROI is) gives the same bytes
    view = frame[100:300, 150:420]
    assert not view.flags.c_contiguous
    assert np.array_equal(back_projection(view, hue_lookup(hist), area[100:300, 150:420], detect),
                          chain[100:300, 150:420])


def test_a_windows_layout_never_makes_the_kernel_compile_again(rig):
    """A window cut from a camera's frame (strided) and a rectangle rendered alone (contiguous) reach
    the one compiled kernel: the loop's warm-up runs the synthetic camera, whose windows are the
    latter, and a real rig's first windows must not find the kernel uncompiled in a paced tick."""
    from core.vision.tracking import backproject_kernel

    frame = Renderer(rig.model, rig.render).render(np.zeros(3), np.array([[0.0, 0.6, 1.0]]), 0.0,
                                                   np.random.default_rng(3))
    area = np.full(frame.shape[:2], 255, np.uint8)
    lut = np.arange(256, dtype=np.uint8)
    cut = back_projection(frame[100:300, 150:420], lut, area[100:300, 150:420], rig.detect)  # both strided
    alone = back_projection(np.ascontiguousarray(frame[100:300, 150:420]), lut, area[100:300, 150:420], rig.detect)
    whole_rows = back_projection(frame[100:300], lut, area[100:300], rig.detect)  # both contiguous
    assert np.array_equal(cut, alone) and np.array_equal(cut, whole_rows[:, 150:420])
    assert len(backproject_kernel.signatures) == 1, backproject_kernel.signatures
