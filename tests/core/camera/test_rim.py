"""The mirror's rim found from its edges in pictures with what real rigs have around the mirror:
black, a grey housing, a lit room, vignetting, and a rim the picture's edge cuts.

Each picture is the synthetic rig's rendered view inside a circle we choose (so the true rim is
known to the pixel), with the surround painted in: real OpenCV on real synthetic images."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from core.camera.guide import find_mirror_rim
from core.camera.render import Renderer

H, W = 480, 640
R = 240.0


@pytest.fixture(scope="module")
def view(camera_config) -> np.ndarray:
    """What the synthetic rig sees: floor, walls, two followers, the leader's own body."""
    r = Renderer(camera_config.model, camera_config.render)
    poses = np.array([[0.5, 0.3, 1.5], [-0.5, 0.6, 1.0]])
    return np.asarray(r.frame(np.array([0.0, 0.0, math.pi / 2]), poses, 0.0, np.random.default_rng(0)))


def picture(view: np.ndarray, centre: tuple[float, float], surround: np.ndarray, vignette: float = 0.0) -> np.ndarray:
    """``view`` moved so that the mirror's centre is at ``centre``, shown inside a circle of radius
    R about it (the true rim), ``surround`` outside; then the lens's vignetting, if any."""
    model_centre = (324.0, 237.0)
    shift = np.float32([[1, 0, centre[0] - model_centre[0]], [0, 1, centre[1] - model_centre[1]]])
    moved = cv2.warpAffine(view, shift, (W, H))
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    out = surround.copy()
    inside = (xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= R * R
    out[inside] = moved[inside]
    if vignette:
        rr = np.hypot(xx - W / 2, yy - H / 2) / math.hypot(W / 2, H / 2)
        out = (out * (1.0 - vignette * rr ** 2)[..., None]).clip(0, 255).astype(np.uint8)
    return out


def surround(kind: str, rng: np.random.Generator) -> np.ndarray:
    if kind == "black":
        return np.zeros((H, W, 3), np.uint8)
    if kind == "grey":  # a dark grey housing, not black: a brightness threshold found nothing here
        return (np.full((H, W, 3), 85.0) + rng.normal(0, 4, (H, W, 3))).clip(0, 255).astype(np.uint8)
    if kind == "lit":  # a lit room around the mirror, brighter than the mirror's picture
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        s = np.repeat((170 + 60 * xx / W)[..., None], 3, axis=2)
        for _ in range(25):
            x0, y0 = int(rng.integers(0, W)), int(rng.integers(0, H))
            ww, hh = (int(v) for v in rng.integers(20, 160, 2))
            s[y0:y0 + hh, x0:x0 + ww] = rng.integers(120, 255, 3)
        return (s + rng.normal(0, 6, s.shape)).clip(0, 255).astype(np.uint8)
    raise ValueError(kind)


CASES = {  # name: (centre, surround, vignetting)
    "black surround": ((324.0, 237.0), "black", 0.0),
    "grey surround": ((325.4, 239.5), "grey", 0.0),
    "lit surround": ((318.2, 242.7), "lit", 0.0),
    "vignetting": ((329.6, 236.1), "grey", 0.9),
    "rim cut by the picture's edge": ((405.4, 259.5), "grey", 0.0),  # a third of the rim is outside the picture
}


@pytest.mark.parametrize("name", list(CASES))
def test_the_rim_is_found_within_3_px_whatever_surrounds_the_mirror(view, name):
    centre, kind, vignette = CASES[name]
    img = picture(view, centre, surround(kind, np.random.default_rng(1)), vignette)
    rim = find_mirror_rim(img)
    assert rim is not None, name
    off = math.hypot(rim.cx - centre[0], rim.cy - centre[1])
    print(f"\n{name}: centre ({rim.cx:.2f}, {rim.cy:.2f}) px, {off:.2f} px from the truth; radius {rim.radius:.2f}"
          f" (true {R:g})")
    assert off <= 3.0 and abs(rim.radius - R) <= 3.0


def test_a_brightness_threshold_would_have_failed_where_the_edges_do_not(view):
    """The grey and lit pictures defeat 'the lit disc inside a dark surround' (the old finder):
    nothing there is darker than 12. The edges still give the rim."""
    for kind in ("grey", "lit"):
        img = picture(view, (325.4, 239.5), surround(kind, np.random.default_rng(2)))
        grey = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        outside = np.hypot(*np.mgrid[0:H, 0:W][::-1] - np.array([325.4, 239.5])[:, None, None]) > R + 2
        assert (grey[outside] > 12).mean() > 0.99
        rim = find_mirror_rim(img)
        assert rim is not None and math.hypot(rim.cx - 325.4, rim.cy - 239.5) <= 3.0


def test_a_picture_without_a_mirror_has_no_rim():
    rng = np.random.default_rng(3)
    assert find_mirror_rim(np.zeros((H, W, 3), np.uint8)) is None
    noise = rng.integers(0, 256, (H, W, 3)).astype(np.uint8)
    assert find_mirror_rim(cv2.GaussianBlur(noise, (0, 0), 3)) is None


def test_calibrate_propose_centre_prints_one_json_line_and_bad_input_is_one_line(view, tmp_path):
    import json

    from tests.helpers import main_cli

    img = tmp_path / "mirror.png"
    cv2.imwrite(str(img), picture(view, (325.4, 239.5), surround("grey", np.random.default_rng(4))))
    res = main_cli("calibrate", "--propose-centre", str(img))
    assert res.returncode == 0, res.stderr
    (line,) = res.stdout.splitlines()
    found = json.loads(line)
    assert set(found) == {"cx", "cy", "r"} and math.hypot(found["cx"] - 325.4, found["cy"] - 239.5) <= 3.0
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.zeros((H, W, 3), np.uint8))
    text = tmp_path / "notes.png"
    text.write_text("not a picture")
    for args, words in (([str(blank)], "no mirror rim found"), ([str(text)], "notes.png"),
                        ([str(tmp_path / "missing.png")], "missing.png"),
                        ([str(img), "--out", str(tmp_path / "c.toml")], "takes one picture and nothing else")):
        res = main_cli("calibrate", "--propose-centre", *args)
        assert res.returncode == 2 and words in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
