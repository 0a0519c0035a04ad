"""The vision pipeline's start-up (paper §3.1-3.2) on synthetic frames with known truth."""

import math
import numpy as np
import pytest
from core.camera.render import Renderer
from core.geometry import heading_world_to_leader, world_to_leader, wrap_angle
from core.sim.team import make_team_state, step_team
from core.types import Commands
from core.vision.blobs import hue_distance_deg
from core.vision.pipeline import VisionPipeline


def run_startup(rig, gamma, p0, a0, seed=0, max_s=40.0):
    """Step the pipeline on rendered frames of a still leader, driving the followers as it asks."""
    n = len(p0)
    renderer = Renderer(rig.model, rig.render)
    pipe = VisionPipeline(n, gamma, rig.working_area, rig.detect, (640, 480), np.random.default_rng(seed))
    state = make_team_state(np.array(p0), np.array(a0))
    rng = np.random.default_rng(seed)
    dt = 1 / 30
    cmd = np.zeros((n, 2))
    t = 0.0
    while t < max_s:
        theta = float(state.leader[2])
        p = world_to_leader(state.followers[:, :2], state.leader[:2], theta)
        a = np.asarray(heading_world_to_leader(state.followers[:, 2], theta))
        out = pipe.step(renderer.render(state.leader, np.column_stack([p, a]), t, rng), dt, (0.0, 0.0, 0.0), cmd)
        if out.ready:
            return out, p, a
        cmd = out.manoeuvre
        state = step_team(state, Commands(cmd[:, 0].copy(), cmd[:, 1].copy()), (0.0, 0.0), dt, t, rng)
        t += dt
    raise AssertionError("start-up did not finish")


@pytest.mark.parametrize("n", [2, 3, 6])
def test_initial_detection_finds_every_follower_with_its_colour_and_heading(rig, gamma, n):
    rng = np.random.default_rng(n)
    ang = np.linspace(0, 2 * math.pi, n, endpoint=False) + rng.uniform(0, 1)
    dist = rng.uniform(0.6, 1.2, n)
    p0 = np.column_stack([-dist * np.sin(ang), dist * np.cos(ang)])
    a0 = rng.uniform(-math.pi, math.pi, n)
    out, p, a = run_startup(rig, gamma, p0, a0, seed=n)
    assert out.tracked.all()
    for i in range(n):
        assert hue_distance_deg(out.hues_deg[i], rig.render.hues_deg[i]) < 8, (i, out.hues_deg)
        assert np.linalg.norm(out.positions[i] - p[i]) < 0.03
        assert abs(math.degrees(wrap_angle(out.headings[i] - a[i]))) < 5.0
