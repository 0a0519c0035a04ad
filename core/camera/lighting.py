"""The floor's light, measured in the working area: how bright it is and its colour cast. A
calibration keeps it (``[lighting]``); a live camera is compared with it now and then, and a
change large enough to hurt tracking (markers found by hue and saturation, the background model
by brightness) is said before tracking suffers. Pure."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.camera.config import WorkingArea

DARKER_OR_BRIGHTER = 0.25  # the floor's brightness changed by more than this share: warn
CAST = 0.12  # the blue/green or red/green balance changed by more than this share: warn


@dataclass(frozen=True)
class Lighting:
    value: float  # median brightness of the floor in the working area (0..255)
    cast_bg: float  # mean blue / mean green there
    cast_rg: float  # mean red / mean green there


def measure_lighting(bgr: np.ndarray, centre: tuple[float, float], area: WorkingArea, step: int = 4) -> Lighting | None:
    """The working area's light, from every ``step``-th pixel (None: no floor in the picture)."""
    img = np.asarray(bgr)
    h, w = img.shape[:2]
    yy, xx = np.mgrid[0:h:step, 0:w:step]
    r = np.hypot(xx - centre[0], yy - centre[1])
    ring = (r >= area.inner_px) & (r <= area.outer_px)
    if ring.sum() < 50:
        return None
    px = img[::step, ::step][ring].astype(np.float64)
    b, g, rr = px[:, 0].mean(), px[:, 1].mean(), px[:, 2].mean()
    value = float(np.median(px.max(axis=1)))
    g = max(g, 1.0)
    return Lighting(value, float(b / g), float(rr / g))


def lighting_change(reference: Lighting, now: Lighting) -> str:
    """'' while the light is as at calibration, else what changed, for people."""
    said = []
    change = now.value / max(reference.value, 1.0) - 1.0
    if abs(change) > DARKER_OR_BRIGHTER:
        said.append(f"the floor is {abs(change) * 100:.0f} % {'darker' if change < 0 else 'brighter'} than at calibration")
    for name, ref, cur in (("blue", reference.cast_bg, now.cast_bg), ("red", reference.cast_rg, now.cast_rg)):
        shift = cur / max(ref, 1e-6) - 1.0
        if abs(shift) > CAST:
            said.append(f"its colour has {'more' if shift > 0 else 'less'} {name} ({abs(shift) * 100:.0f} %)")
    if not said:
        return ""
    return "lighting: " + ", ".join(said) + ": marker hues and the background may no longer match; fix the light or" \
        " lock the camera's exposure and white balance ([capture]) and recalibrate"
