"""static_config/default.toml (or --config FILE): what `omniformation run` starts with."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from core.config import ConfigError, MeasurementNoise, Table, parse_dynamics, parse_measurement, toml_loads
from core.link.spec import forms, parse_spec
from core.sim.team import FollowerDynamics

from app.contracts import Rig
from app.files import (DEFAULT_CONFIG, SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, UserError, display_path,
                       load_synthetic_rig)

__all__ = ["DEFAULT_CONFIG", "FEEDBACKS", "ServiceConfig", "load_service_config"]
FEEDBACKS = ("vision", "truth")
CONFIG_LINKS = ("sim", "none", "serial")  # the link schemes service.link may name (core.link.spec)


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
    max_total_bytes: int = 20 * 10**9  # [recording] max_total_gb: sessions in recordings/ together
    free_floor_bytes: int = 500 * 10**6  # [recording] free_space_floor_mb: recording stops below this

    def camera(self) -> Rig:
        """The synthetic rig and its Γ, read and checked (one-line UserError otherwise)."""
        return load_synthetic_rig(self.rig_path, self.calibration_path)


def load_service_config(path: Path, max_followers: int) -> ServiceConfig:
    if not path.is_file():
        raise UserError(f"{path}: no such config file")
    source = display_path(path)
    try:
        data = toml_loads(path.read_text(encoding="utf-8"), source)
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{source}: cannot read: {exc}") from None
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    try:
        top = Table(data, source, "")
        svc = top.table("service")
        rate = svc.number("rate_hz", 1.0, 200.0, default=30.0, unit="Hz")
        followers = svc.integer("followers", 1, max_followers, default=3)
        seed = svc.integer("seed", 0, 2**32 - 1, default=0)
        feedback = svc.text("feedback", default="vision", choices=FEEDBACKS)
        link = svc.text("link", default="sim")
        try:
            parse_spec(link, "service.link", CONFIG_LINKS)  # the link registry's grammar (core.link.spec)
        except ValueError:
            raise svc.fail("link", link, f"{forms(CONFIG_LINKS)} (e.g. serial:/dev/ttyUSB0)") from None
        svc.finish()
        cam = top.table("camera")
        frames = cam.text("source", default="synthetic")
        # given paths are relative to the config file; without them, the shipped synthetic rig
        rig = path.parent / cam.text("rig") if cam.has("rig") else SYNTHETIC_CAMERA
        calibration = path.parent / cam.text("calibration") if cam.has("calibration") else SYNTHETIC_CALIBRATED
        cam.finish()
        dynamics = parse_dynamics(top.table("dynamics"))
        measurement = parse_measurement(top.table("measurement"))
        rec = top.table("recording")
        max_total = rec.number("max_total_gb", 0.01, 100_000.0, default=20.0, unit="GB")
        floor = rec.number("free_space_floor_mb", 0.0, 1_000_000.0, default=500.0, unit="MB")
        rec.finish()
        top.finish()
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    if frames != "synthetic" and link == "sim":
        raise UserError(f"{source}: camera.source = {frames!r} is a real rig: service.link must be 'serial:PATH' or"
                        " 'none', not 'sim'")
    return ServiceConfig(path, source, rate, followers, seed, feedback, link, frames, rig, calibration, dynamics,
                         measurement, int(max_total * 1e9), int(floor * 1e6))
