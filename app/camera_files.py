"""Reading camera configs, matching tables and images for the CLI (file I/O around core.camera)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from app.paths import SYNTHETIC_CALIBRATED, SYNTHETIC_CAMERA, UserError, display_path
from core.camera.config import CameraConfig, parse_camera
from core.camera.gamma import CalibrationError, Gamma, MatchingTable, parse_table
from core.config import ConfigError

__all__ = ["SYNTHETIC_CALIBRATED", "SYNTHETIC_CAMERA", "load_camera", "load_calibration", "load_synthetic_rig",
           "require_gamma", "load_table", "write_table", "read_image", "check_out_path"]


def _read_text(path: Path, what: str) -> str:
    if not path.is_file():
        raise UserError(f"{path}: no such {what} file")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{display_path(path)}: cannot read: {exc}") from None


def load_camera(path: Path) -> CameraConfig:
    try:
        return parse_camera(_read_text(path, "camera config"), display_path(path))
    except (ConfigError, CalibrationError) as exc:
        raise UserError(str(exc)) from None


def load_calibration(path: Path) -> tuple[CameraConfig, Gamma]:
    """A rig's calibration file (working area, detection, Γ) and its Γ; one-line UserError without Γ."""
    cfg = load_camera(path)
    return cfg, require_gamma(cfg)


def require_gamma(cfg: CameraConfig) -> Gamma:
    """``cfg.require_gamma()`` with its one-line message as a UserError."""
    try:
        return cfg.require_gamma()
    except ConfigError as exc:
        raise UserError(str(exc)) from None


def load_synthetic_rig(rig_path: Path, calibration_path: Path) -> tuple[CameraConfig, Gamma]:
    """A synthetic rig that renders frames and the Γ that reads them, each checked (one-line UserError)."""
    rig = load_camera(rig_path)
    if rig.model is None:
        raise UserError(f"{display_path(rig_path)}: has no [model]: a synthetic rig is needed to render frames")
    return rig, load_calibration(calibration_path)[1]


def load_table(path: Path) -> MatchingTable:
    try:
        return parse_table(_read_text(path, "matching table"), display_path(path))
    except CalibrationError as exc:
        raise UserError(str(exc)) from None


def write_table(table: MatchingTable, path: Path) -> None:
    lines = ["bearing_deg,metres,u,v"]
    lines += [f"{b:g},{d:g},{u:.3f},{v:.3f}" for b, d, u, v in zip(table.bearing_deg, table.metres, table.u, table.v)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def read_image(path: Path) -> np.ndarray:
    if not path.is_file():
        raise UserError(f"{path}: no such image file")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise UserError(f"{display_path(path)}: not an image OpenCV can read (PNG, JPEG, BMP, ...)")
    return img


def check_out_path(path: Path) -> None:
    if not path.parent.exists():
        raise UserError(f"{path}: folder {path.parent} does not exist")
