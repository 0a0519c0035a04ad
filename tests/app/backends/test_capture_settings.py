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


def _view() -> np.ndarray:
    from core.camera.render import Renderer

    rig = parse_camera((ROOT / "static_config" / "camera" / "synthetic.toml").read_text(), "synthetic.toml")
    poses = np.array([[0.5, 0.3, 1.5], [-0.5, 0.6, 1.0]])
    return np.asarray(Renderer(rig.model, rig.render).frame(np.array([0.0, 0.0, np.pi / 2]), poses, 0.0,
                                                            np.random.default_rng(0)))


def test_the_lighting_monitor_says_when_the_floor_is_darker_or_its_colour_moved():
    from core.camera.config import WorkingArea
    from core.camera.lighting import lighting_change, measure_lighting

    view, area, centre = _view(), WorkingArea(55.0, 195.0), (324.0, 237.0)
    ref = measure_lighting(view, centre, area)
    assert ref is not None and 40 < ref.value < 250
    same = measure_lighting((view * 1.1).clip(0, 255).astype(np.uint8), centre, area)
    assert lighting_change(ref, same) == ""  # 10 % brighter: fine
    dark = measure_lighting((view * 0.6).astype(np.uint8), centre, area)
    assert "the floor is 40 % darker than at calibration" in lighting_change(ref, dark)
    bluer = view.astype(np.float64)
    bluer[..., 0] *= 1.3
    said = lighting_change(ref, measure_lighting(bluer.clip(0, 255).astype(np.uint8), centre, area))
    assert "more blue" in said and "darker" not in said


def test_a_live_camera_in_other_light_than_its_calibration_is_said_on_the_status(tmp_path):
    """The calibration keeps the floor's light ([lighting]); the loop on a camera whose pictures
    are 40 % darker says so in its camera state (the page's status, and every recorded tick)."""
    import threading

    from app.backends.camera import FolderSource
    from app.backends.hardware import HardwareTeam
    from app.contracts import Rig
    from app.live.loop import ServiceLoop
    from app.backends.world import Backends
    from app.params import ParamsStore
    from core.camera.config import gamma_toml
    from core.camera.lighting import measure_lighting

    view = _view()
    calibrated = parse_camera(CAMERA, "cam.toml")
    light = measure_lighting(view, (calibrated.gamma.cx, calibrated.gamma.cy), calibrated.working_area)
    text = gamma_toml(calibrated.gamma, calibrated.working_area, calibrated.detect, "test",
                      (light.value, light.cast_bg, light.cast_rg))
    rig = parse_camera(text, "cam.toml")
    assert rig.lighting == pytest.approx((light.value, light.cast_bg, light.cast_rg), rel=1e-4)
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), (view * 0.6).astype(np.uint8))
    source = FolderSource(tmp_path, fps=30.0, loop=True)
    loop = ServiceLoop(ParamsStore(), Backends(frames=source, hardware=HardwareTeam(2),
                                               camera=Rig(rig, rig.require_gamma())), rate_hz=30.0)
    states: list = []
    loop.subscribe(states.append)
    thread = threading.Thread(target=loop.run, daemon=True)
    thread.start()
    try:
        wait_for(lambda: any("darker than at calibration" in s.camera_state for s in states), 20, "the lighting note")
    finally:
        loop.stop()
        thread.join(10)
        source.close()
