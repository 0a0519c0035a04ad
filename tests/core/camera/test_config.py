"""Camera config files: parsed, and bad values named in one line."""

import pytest
from core.camera.config import WorkingArea, parse_camera
from core.config import ConfigError


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
