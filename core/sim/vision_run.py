"""Closed loop with vision: simulator → synthetic frame → pipeline → controller → simulator.

The loop itself is the stepped simulator's (core.sim.stepped) with the vision pipeline as
feedback; this module keeps the name the paper's runs are called by.
"""

from __future__ import annotations

from collections.abc import Callable

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.config import Scenario
from core.sim.stepped import VisionLog, simulate_stepped
from core.types import Image
from core.vision.pipeline import PipelineSettings

__all__ = ["VisionLog", "simulate_vision"]


def simulate_vision(
    scenario: Scenario,
    rig: CameraConfig,
    gamma: Gamma,
    settings: PipelineSettings = PipelineSettings(),
    max_startup_s: float = 60.0,
    on_frame: Callable[[int, Image], None] | None = None,
) -> VisionLog:
    """Run ``scenario`` with the controller fed by the vision pipeline on rendered frames.

    ``on_frame(k, frame)`` sees every frame (row k of the log), e.g. to record it;
    ``np.asarray(frame)`` renders the whole of it."""
    if rig.model is None:
        raise ValueError(f"{rig.source}: a vision simulation needs the rig's [model]")
    run = simulate_stepped(scenario, rig, gamma, settings, max_startup_s, on_frame)
    assert run.vision is not None
    return run.vision
