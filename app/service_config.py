"""static_config/default.toml (or --config FILE): what `omniformation run` starts with."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.config import ConfigError, MeasurementNoise, Table, parse_dynamics, parse_measurement
from core.sim.team import FollowerDynamics

from app.backends.serial_link import parse_link_spec
from app.camera_files import load_synthetic_rig
from app.paths import DEFAULT_CONFIG, UserError, display_path

__all__ = ["DEFAULT_CONFIG", "FEEDBACKS", "ServiceConfig", "load_service_config"]
FEEDBACKS = ("vision", "truth")


@dataclass(frozen=True)
class ServiceConfig:
    path: Path
    source: str
    rate_hz: float
    followers: int
    seed: int
    feedback: str
    link: str  # "sim" or "serial:PATH" (a real rig: also "none")
    frames: str  # "synthetic", or a real camera: an index, a device, a video file or a folder
    rig_path: Path
    calibration_path: Path
    dynamics: FollowerDynamics
    measurement: MeasurementNoise

    def camera(self) -> tuple[CameraConfig, Gamma]:
        """The synthetic rig and its Γ, read and checked (one-line UserError otherwise)."""
        return load_synthetic_rig(self.rig_path, self.calibration_path)


def load_service_config(path: Path, max_followers: int) -> ServiceConfig:
    if not path.is_file():
        raise UserError(f"{path}: no such config file")
    source = display_path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{source}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{source}: not valid TOML: {exc}") from None
    try:
        top = Table(data, source, "")
        svc = top.table("service")
        rate = svc.number("rate_hz", 1.0, 200.0, default=30.0, unit="Hz")
        followers = svc.integer("followers", 1, max_followers, default=3)
        seed = svc.integer("seed", 0, 2**32 - 1, default=0)
        feedback = svc.text("feedback", default="vision", choices=FEEDBACKS)
        link = svc.text("link", default="sim")
        if link != "none":
            try:
                parse_link_spec(link)
            except ValueError:
                raise svc.fail("link", link, "'sim', 'none' or 'serial:PATH' (e.g. serial:/dev/ttyUSB0)") from None
        svc.finish()
        cam = top.table("camera")
        frames = cam.text("source", default="synthetic")
        rig = path.parent / cam.text("rig", default="camera/synthetic.toml")
        calibration = path.parent / cam.text("calibration", default="camera/synthetic_calibrated.toml")
        cam.finish()
        dynamics = parse_dynamics(top.table("dynamics"))
        measurement = parse_measurement(top.table("measurement"))
        top.finish()
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    if frames != "synthetic" and link == "sim":
        raise UserError(f"{source}: camera.source = {frames!r} is a real rig: service.link must be 'serial:PATH' or"
                        " 'none', not 'sim'")
    return ServiceConfig(path, source, rate, followers, seed, feedback, link, frames, rig, calibration, dynamics,
                         measurement)
