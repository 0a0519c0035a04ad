"""A real camera is set as its camera file's [capture] says before its first frame, and what it
took is read back and shown: a stand-in driver records every call made to it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from app.backends.camera import CaptureSource, settings_text
from core.camera.config import CaptureSettings, parse_camera
from core.config import ConfigError
from tests.helpers import ROOT, wait_for


class Driver:
    """A camera driver as OpenCV sees one: it takes some settings, clamps others (no more than
    1280x720), knows only the V4L2 value 1 for manual exposure, and hands out frames."""

    calls: list[tuple[str, int, float]] = []

    def __init__(self, target: int | str) -> None:
        self.props: dict[int, float] = {cv2.CAP_PROP_AUTO_EXPOSURE: 3.0, cv2.CAP_PROP_AUTO_WB: 1.0}
        Driver.calls = []

    def isOpened(self) -> bool:  # noqa: N802 - OpenCV's name
        return True

    def set(self, prop: int, value: float) -> bool:
        Driver.calls.append(("set", prop, value))
        if prop == cv2.CAP_PROP_FRAME_WIDTH:
            value = min(value, 1280.0)
        elif prop == cv2.CAP_PROP_FRAME_HEIGHT:
            value = min(value, 720.0)
        elif prop == cv2.CAP_PROP_AUTO_EXPOSURE and value not in (1.0, 3.0):
            return False
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        return self.props.get(prop, 0.0)

    def read(self) -> tuple[bool, np.ndarray]:
        Driver.calls.append(("read", 0, 0.0))
        return True, np.full((720, 1280, 3), 90, np.uint8)

    def release(self) -> None:
        pass


ASKED = CaptureSettings(width=1920, height=1080, fps=30.0, pixel_format="MJPG", exposure=120.0, gain=4.0,
                        white_balance_k=4500.0, buffer_size=1)


def test_settings_are_applied_before_the_first_frame_and_read_back():
    source = CaptureSource(0, is_file=False, settings=ASKED, opener=Driver)
    try:
        wait_for(lambda: source.latest()[0] is not None, 10, "a frame")
    finally:
        source.close()
    calls = Driver.calls
    first_read = next(k for k, c in enumerate(calls) if c[0] == "read")
    sets = [(prop, value) for kind, prop, value in calls[:first_read] if kind == "set"]
    props = [prop for prop, _ in sets]
    assert all(c[0] == "read" for c in calls[first_read:])  # nothing is changed once frames flow
    assert props[0] == cv2.CAP_PROP_FOURCC and sets[0][1] == cv2.VideoWriter.fourcc(*"MJPG")  # the format first
    assert props.index(cv2.CAP_PROP_FRAME_WIDTH) < props.index(cv2.CAP_PROP_EXPOSURE)
    assert (cv2.CAP_PROP_AUTO_EXPOSURE, 1.0) in sets  # manual exposure, the value this driver knows
    assert props.index(cv2.CAP_PROP_AUTO_EXPOSURE) < props.index(cv2.CAP_PROP_EXPOSURE)
    assert (cv2.CAP_PROP_AUTO_WB, 0.0) in sets and props.index(cv2.CAP_PROP_AUTO_WB) < props.index(cv2.CAP_PROP_WB_TEMPERATURE)
    assert (cv2.CAP_PROP_BUFFERSIZE, 1.0) in sets
    report = source.settings_report
    assert report["width"] == (1920, 1280.0) and report["height"] == (1080, 720.0)  # asked, got
    assert report["exposure"] == (120.0, 120.0) and report["auto_exposure"] == ("off", "off")
    assert report["white_balance_k"] == (4500.0, 4500.0) and report["pixel_format"] == ("MJPG", "MJPG")
    line = source.settings_line
    assert "width 1920 (got 1280)" in line and "exposure 120," in line and "not locked" not in line


def test_what_is_not_locked_is_said():
    assert "none locked" in settings_text({}, None)
    line = settings_text({"width": (640, 640.0)}, CaptureSettings(width=640))
    assert line.endswith("not locked: exposure, white balance") and "(got" not in line


CAMERA = (ROOT / "static_config" / "camera" / "synthetic_calibrated.toml").read_text()


def test_the_capture_table_is_read_and_bad_values_are_one_line():
    camera = parse_camera(CAMERA + "\n[capture]\nwidth = 640\nheight = 480\nfps = 30\npixel_format = \"YUYV\"\n"
                                   "exposure = 150\ngain = 2\nwhite_balance_k = 4000\n", "cam.toml")
    assert camera.capture == CaptureSettings(640, 480, 30.0, "YUYV", 150.0, 2.0, 4000.0, 1)
    assert camera.capture.asked()["white_balance_k"] == 4000.0
    assert parse_camera(CAMERA, "cam.toml").capture is None
    for extra, words in (("pixel_format = \"MJPEG\"", "capture.pixel_format = 'MJPEG': must be a four-character"),
                         ("white_balance_k = 90000", "capture.white_balance_k = 90000: must be a number in"),
                         ("fps = 0", "capture.fps = 0: must be a number in (0"),
                         ("exposre = 100", "capture.exposre is not a known key (known here: buffer_size, exposure")):
        with pytest.raises(ConfigError) as info:
            parse_camera(CAMERA + f"\n[capture]\n{extra}\n", "cam.toml")
        assert words in str(info.value) and "\n" not in str(info.value)
