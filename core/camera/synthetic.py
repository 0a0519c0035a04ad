"""A synthetic rig end to end: render frames from a camera config, measure a matching table.

``synthetic_table`` does what a person does on a real rig (docs/calibration.md): put one
marker — a follower-sized box with its coloured rectangle, at the rectangles' height —
at each known bearing and distance on a cleared floor, take a picture, and note the
pixel of the marker's centre (here: the centroid of the colour blob found in the
picture, exactly as ``locate`` finds it). The table is then fitted by the same
:func:`core.camera.gamma.fit_gamma` a real table goes through.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from core.camera.config import CameraConfig
from core.camera.gamma import CalibrationError, MatchingTable
from core.camera.model import CameraModel, bearing_range_to_xy
from core.camera.render import Renderer
from core.vision.blobs import find_blobs


def require_model(config: CameraConfig) -> CameraModel:
    if config.model is None:
        raise CalibrationError(f"{config.source}: has no [model] section, so it cannot be rendered")
    return config.model


def renderer_for(config: CameraConfig, **render_changes: object) -> Renderer:
    return Renderer(require_model(config), replace(config.render, **render_changes))  # type: ignore[arg-type]  # names and types are RenderSettings fields, as the callers give them


def synthetic_table(config: CameraConfig, rng: np.random.Generator) -> MatchingTable:
    """Render one marker at a time at each (bearing, distance) of the plan; find its blob."""
    model = require_model(config)
    renderer = renderer_for(config, clutter=False, distractor=False)
    area = config.working_area.mask(model.width, model.height, model.center)
    hue = config.render.hues_deg[0]
    rows: list[tuple[float, float, float, float]] = []
    height = config.render.follower.height_m + 0.002
    for b_deg in config.calibration.bearings_deg:
        for d in config.calibration.distances_m:
            b = math.radians(b_deg)
            xy = bearing_range_to_xy(np.array(b), np.array(d))
            expected = model.project(np.array([float(xy[0]), float(xy[1]), height]))
            frame = renderer.render(np.array([0.0, 0.0, math.pi / 2]), np.array([[xy[0], xy[1], b + math.pi / 2]]),
                                    0.0, rng)
            blobs = [bl for bl in find_blobs(frame, area, config.detect) if abs(((bl.hue_deg - hue + 180) % 360) - 180) < 20]
            if not blobs:
                continue  # outside the working area or hidden: a person would skip it too
            best = min(blobs, key=lambda bl: math.hypot(bl.u - expected[0], bl.v - expected[1]))
            rows.append((b_deg, d, best.u, best.v))
    if not rows:
        raise CalibrationError(f"{config.source}: no calibration marker was visible in the working area")
    arr = np.array(rows)
    return MatchingTable(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3])
