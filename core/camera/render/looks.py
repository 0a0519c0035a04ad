"""How the synthetic world looks: marker hues, robot-like boxes, render settings.

``DEFAULT_HUES_DEG`` is the one list of follower marker hues: the renderer paints them, the
pipeline learns them, and the dashboard and figures draw each follower in its marker's colour.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import cv2
import numpy as np

from core.types import FloatArray

# One hue per follower, as far apart as the first few allow (degrees, OpenCV hue x 2).
DEFAULT_HUES_DEG: tuple[float, ...] = (0.0, 120.0, 240.0, 60.0, 300.0, 180.0, 30.0, 270.0)


@dataclass(frozen=True)
class BoxLook:
    """A robot-like box: a body and, optionally, one coloured rectangle on top."""

    length_m: float = 0.25  # along the heading (paper: 15 x 25 cm, 10 cm high)
    width_m: float = 0.15
    height_m: float = 0.10
    top_length_m: float = 0.18
    top_width_m: float = 0.11


@dataclass(frozen=True)
class RenderSettings:
    """How the synthetic camera's pictures look (static_config/camera/*.toml, [render])."""

    hues_deg: tuple[float, ...] = DEFAULT_HUES_DEG
    marker_saturation: float = 0.85
    marker_value: float = 0.85
    follower: BoxLook = BoxLook()
    noise_sigma: float = 3.0  # sensor noise, grey levels (sigma)
    blur_sigma_px: float = 0.7  # optics; 0 = none
    jpeg_quality: int = 0  # 0 = no JPEG round trip; 1..100 = quality
    drift_gain: float = 0.12  # lighting: gain varies by +- this fraction
    drift_offset: float = 6.0  # and brightness by +- this many grey levels
    drift_period_s: float = 37.0
    clutter: bool = True  # grey boxes on the floor (every clutter_period_m, repeating)
    distractor: bool = True  # a coloured box that is not a robot
    distractor_hue_deg: float = 150.0
    clutter_period_m: float = 4.0
    floor_far_m: float = 4.0  # where the floor meets the walls
    texture_seed: int = 7


def follower_bgr(i: int) -> tuple[int, int, int]:
    """Follower i's colour wherever it is drawn for people (the page, the figures): its
    marker's hue from ``DEFAULT_HUES_DEG``, a little darker so it reads on white."""
    b, g, r = marker_bgr(DEFAULT_HUES_DEG[i % len(DEFAULT_HUES_DEG)], 0.85, 0.8)
    return int(b), int(g), int(r)


def follower_rgb(i: int) -> tuple[int, int, int]:
    b, g, r = follower_bgr(i)
    return r, g, b


def hue_rgb(hue_deg: float) -> tuple[int, int, int]:
    """An arena robot's marker hue as a bright RGB for people (the fleet page's 3D view, Foxglove's)."""
    r, g, b = colorsys.hsv_to_rgb((hue_deg % 360.0) / 360.0, 0.85, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def follower_hex(i: int) -> str:
    """``follower_rgb`` as '#rrggbb' (matplotlib, uPlot)."""
    return "#{:02x}{:02x}{:02x}".format(*follower_rgb(i))


def marker_bgr(hue_deg: float, saturation: float, value: float) -> tuple[float, float, float]:
    """BGR (0..255 floats) of a marker colour."""
    hsv = np.array([[[hue_deg / 2.0 % 180.0, saturation * 255.0, value * 255.0]]], dtype=np.float32)
    bgr = cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2BGR)[0, 0]
    return float(bgr[0]), float(bgr[1]), float(bgr[2])


@dataclass(frozen=True)
class Boxes:
    """Boxes in the leader frame, one row each: centre (x, y), heading a (rad, from +x),
    size (length, width, height, marker length, marker width; m), body and marker colour
    (BGR 0..255; a marker colour of NaN: no marker)."""

    x: FloatArray
    y: FloatArray
    a: FloatArray
    dims: FloatArray  # (m, 5)
    body_bgr: FloatArray  # (m, 3)
    top_bgr: FloatArray  # (m, 3)

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @staticmethod
    def empty() -> "Boxes":
        z = np.zeros(0)
        return Boxes(z, z, z, np.zeros((0, 5)), np.zeros((0, 3)), np.zeros((0, 3)))


def look_dims(look: BoxLook) -> tuple[float, float, float, float, float]:
    return (look.length_m, look.width_m, look.height_m, look.top_length_m, look.top_width_m)
