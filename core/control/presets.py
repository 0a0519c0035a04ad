"""The formation presets of the page and the scenarios: slots (n, 2) in the leader frame.

Every preset keeps its robots at least ``MIN_SPACING_M`` apart centre to centre (and from the
leader), more than the safety filter's default barrier (core.control.safety), so that a team
that reaches its slots leaves the filter inactive: a preset the filter could not allow would
leave the formation error standing for ever.
"""

from __future__ import annotations

import numpy as np

from core.types import FloatArray

MIN_SPACING_M = 0.36  # the filter keeps 0.25 m between centres through points 2.5 cm ahead of each axle
# (SafetySettings.projection_m), so two robots facing each other touch its barrier at 0.25 + 2 x 0.025 =
# 0.30 m: a settled team must be further apart

FORMATION_PRESETS = ("paper triangle", "triangle ahead", "line abreast", "column", "V", "diamond", "ring")


PRESET_REACH_M = 1.5  # presets stay inside the camera's working ring


def default_formation(n: int) -> FloatArray:
    """A sensible formation for n followers: the paper's triangle for 2, a V or ring beyond."""
    return formation_preset("paper triangle" if n <= 2 else "V" if n <= 5 else "ring", n)


def formation_preset(name: str, n: int) -> FloatArray:
    """Slots (n, 2) in the leader frame for a named formation, shrunk to fit within 1.5 m."""
    slots = _preset_shape(name, n)
    reach = float(np.abs(slots).max()) if slots.size else 0.0
    return slots * (PRESET_REACH_M / reach) if reach > PRESET_REACH_M else slots


def _preset_shape(name: str, n: int) -> FloatArray:
    i = np.arange(n, dtype=np.float64)
    if name == "paper triangle":  # §4: (-0.5, -0.3), (0.5, -0.3), more behind
        side = np.where(i % 2 == 0, -1.0, 1.0)
        row = i // 2
        return np.column_stack([side * 0.5 * (1 + row), -0.3 - 0.4 * row])
    if name == "triangle ahead":  # §5.1: (-0.6, 0.3), (0.6, 0.3)
        side = np.where(i % 2 == 0, -1.0, 1.0)
        row = i // 2
        return np.column_stack([side * 0.6 * (1 + row), 0.3 + 0.4 * row])
    if name == "line abreast":
        k = i // 2 + 1
        side = np.where(i % 2 == 0, -1.0, 1.0)
        return np.column_stack([side * 0.5 * k, np.zeros(n)])
    if name == "column":  # one file; from 5 robots on two files side by side, so neighbours keep MIN_SPACING_M
        if n <= 4:
            spacing = min(0.5, 1.1 / max(n - 1, 1))
            return np.column_stack([np.zeros(n), -(0.4 + spacing * i)])
        return np.column_stack([np.where(i % 2 == 0, -0.19, 0.19), -(0.4 + 0.38 * (i // 2))])
    if name == "V":
        k = i // 2 + 1
        side = np.where(i % 2 == 0, -1.0, 1.0)
        return np.column_stack([side * 0.4 * k, -0.4 * k])
    if name == "diamond":
        base = np.array([[-0.5, -0.5], [0.5, -0.5], [0.0, -1.0], [0.0, 0.6]])
        k = np.arange(max(n - 4, 0), dtype=np.float64)  # more robots on a wider ring, clear of the four corners
        ang = np.pi / 4 + 2 * np.pi * k / max(n - 4, 1)
        extra = 1.25 * np.column_stack([np.cos(ang), np.sin(ang)])
        return np.vstack([base[: min(n, 4)], extra])
    if name == "ring":
        ang = np.pi / 2 + 2 * np.pi * i / max(n, 1)
        return np.column_stack([0.9 * np.cos(ang), 0.9 * np.sin(ang)])
    raise ValueError(f"formation {name!r}: must be one of {', '.join(FORMATION_PRESETS)}")


def spacing(slots: FloatArray) -> float:
    """The smallest centre distance between two slots or a slot and the leader (the origin)."""
    pts = np.vstack([np.zeros((1, 2)), np.asarray(slots, dtype=np.float64).reshape(-1, 2)])
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    d[np.diag_indices_from(d)] = np.inf
    return float(d.min())
