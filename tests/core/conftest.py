"""The synthetic rig and its calibrated Γ, read once per module that asks for them."""

import pytest

from core.camera.config import CameraConfig, parse_camera
from core.camera.gamma import Gamma
from tests.helpers import ROOT

SYNTHETIC = "static_config/camera/synthetic.toml"


@pytest.fixture(scope="module")
def camera_config() -> CameraConfig:
    return parse_camera((ROOT / SYNTHETIC).read_text(), SYNTHETIC)


@pytest.fixture(scope="module")
def rig(camera_config: CameraConfig) -> CameraConfig:
    return camera_config


@pytest.fixture(scope="module")
def gamma() -> Gamma:
    path = ROOT / "static_config/camera/synthetic_calibrated.toml"
    g = parse_camera(path.read_text(), path.name).gamma
    assert g is not None
    return g
