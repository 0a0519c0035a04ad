"""One scenario run, whichever simulator it needs: the kernel for plain truth runs, the stepped
simulator for obstacles, the filter, a goal, switches or latency, and for vision in the loop.
`simulate`, `rerun` and every study run come through here, so a study's run and `simulate` of the
same scenario with the same seed are the same run."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from core.camera.config import CameraConfig
from core.camera.gamma import Gamma
from core.config import Scenario
from core.sim.run import SimulationLog, simulate
from core.sim.stepped import SafetyLog, VisionLog, simulate_stepped
from core.types import Image
from core.vision.pipeline import PipelineSettings


@dataclass(frozen=True)
class ScenarioRun:
    log: SimulationLog
    vision: VisionLog | None = None
    safety: SafetyLog | None = None  # the stepped simulator's (obstacles, the filter, a goal, switches, latency)


def run_scenario(scenario: Scenario, rig: CameraConfig | None = None, gamma: Gamma | None = None,
                 settings: PipelineSettings = PipelineSettings(),
                 on_frame: Callable[[int, Image], None] | None = None) -> ScenarioRun:
    """The scenario with ground-truth feedback (plus its noise), or with ``rig`` and ``gamma``
    through the vision pipeline; ``on_frame(k, frame)`` sees every rendered frame."""
    vision = rig is not None and gamma is not None
    if not vision and not scenario.stepped:
        return ScenarioRun(simulate(scenario))
    if vision and rig is not None and rig.model is None:
        raise ValueError(f"{rig.source}: a vision simulation needs the rig's [model]")
    run = simulate_stepped(scenario, rig if vision else None, gamma if vision else None, settings, on_frame=on_frame)
    return ScenarioRun(run.log, run.vision, run.safety)
