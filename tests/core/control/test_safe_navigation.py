"""Safe team navigation end to end in the stepped simulator (core.sim.stepped): the
scenarios by name with ground truth and with vision in the loop, against what safe navigation must keep:
no robot nearer than the minimum distance to another or 10 cm to an obstacle's surface, the
leader at its goal, the formation held after the gap, and the paper's runs untouched."""

from __future__ import annotations

import re

import numpy as np
import pytest

from app.files import load_scenario
from core.config import Scenario
from core.control.navigation import NavSettings, navigate
from core.control.safety import SafetySettings
from core.sim.run import simulate
from core.sim.stepped import SteppedRun, simulate_stepped

FOLLOWER_RADIUS = 0.15  # a 15 x 25 cm follower as a disc
LEADER_RADIUS = 0.25
CLEARANCE = 0.10  # no robot within 0.10 m of an obstacle's surface: what every run here must keep


def _check_clear_and_at_goal(name: str, run: SteppedRun, scenario: Scenario) -> None:
    log, sf = run.log, run.safety
    after = log.t >= 0
    err = np.linalg.norm(log.p - log.p_d, axis=-1)
    steady = after & (log.t >= sf.goal_reached_s)
    rms = float(np.sqrt(np.mean(err[steady] ** 2)))
    print(f"\n{name}: goal reached at {sf.goal_reached_s:.1f} s; closest robots {sf.min_distance[after].min() * 100:.1f} cm;"
          f" follower bodies {(sf.obstacle_gap[after].min() - FOLLOWER_RADIUS) * 100:.1f} cm and the leader's"
          f" {(sf.leader_gap[after].min() - LEADER_RADIUS) * 100:.1f} cm from an obstacle; narrowest formation"
          f" {sf.scale.min():.2f}; formation error after the goal {rms * 100:.2f} cm RMS;"
          f" filter acted on {sum(s == 'filtered' for s in sf.status)} ticks, failed on"
          f" {sum(s in ('infeasible', 'no solver') for s in sf.status)}")
    assert np.isfinite(sf.goal_reached_s)
    assert np.hypot(*(log.leader[-1, :2] - np.array(scenario.leader.goal))) <= 0.06  # type: ignore[union-attr]
    assert sf.min_distance[after].min() >= 0.25
    assert sf.obstacle_gap.min() >= FOLLOWER_RADIUS + CLEARANCE
    assert sf.leader_gap.min() >= LEADER_RADIUS + CLEARANCE
    assert sf.scale.min() < 0.9 or name.startswith("obstacle")  # the gap is narrower than the formation
    assert sf.scale[-1] == pytest.approx(1.0)  # and it grew back
    assert steady.sum() > 10 * scenario.rate_hz and rms <= 0.02


def test_narrow_gap_with_ground_truth():
    s = load_scenario("narrow_gap")
    _check_clear_and_at_goal("narrow_gap, truth", simulate_stepped(s), s)


@pytest.mark.parametrize("name, seconds", [("narrow_gap", 100.0), ("obstacle_course", 145.0)])
def test_with_vision_in_the_loop(name, seconds, rig, gamma):
    """Each run ends some 22 s after its goal (reached at 77.7 and 120.9 s with vision; the files
    run on to 110 and 180 s for the page): the formation is judged over the last 10 s or more, as
    _check_clear_and_at_goal asks, and a goal reached later than that fails it."""
    s = load_scenario(name).replace(duration_s=seconds)
    run = simulate_stepped(s, rig, gamma)
    assert run.vision is not None and run.safety.scan_ranges is not None  # the filter saw the scan, not the truth
    _check_clear_and_at_goal(f"{name}, vision", run, s)


def _swaps(s: Scenario, rig=None, gamma=None) -> tuple[int, int, float, float]:
    """(ticks two robots are under the minimum distance, switches where that happens, closest
    centres, settled formation error: per switch the mean over the last 2 s of its window,
    the median over the switches)."""
    run = simulate_stepped(s, rig, gamma)
    log, sf = run.log, run.safety
    after = log.t >= 0
    every = s.switches[1][0] - s.switches[0][0]
    under = after & (sf.min_distance < 0.25)
    err = np.linalg.norm(log.p - log.p_d, axis=-1).mean(axis=1)
    settled = after & (np.mod(log.t, every) >= every - 2.0)
    window = (log.t[settled] // every).astype(int)
    per_switch = [err[settled][window == w].mean() for w in np.unique(window)]
    return int(under.sum()), len(set((log.t[under] // every).astype(int))), float(sf.min_distance[after].min()), \
        float(np.median(per_switch))


def _preset_swaps(seed: int, switches: int) -> Scenario:
    """preset_swaps with its presets drawn from ``seed``, ``switches`` of them. The shipped seed's
    first 33 switches happen to bring no two robots together: these seeds do within their first
    six (without the filter, truth: seed 9 in switches 1, 3, 4 and 5, closest 11.8 cm; seed 24 in
    1, 2 and 3), so a short run meets the dangerous switches a 100-switch run met at 33-35."""
    from core.config import parse_scenario
    from tests.helpers import ROOT

    text = (ROOT / "static_config" / "scenarios" / "preset_swaps.toml").read_text()
    text = re.sub(r"^seed = \d+", f"seed = {seed}", text, flags=re.M)
    text = re.sub(r"^duration_s = [\d.]+", f"duration_s = {switches * 20.0 + 10.0}", text, flags=re.M)
    return parse_scenario(text, f"preset_swaps (seed {seed})")


# with vision, five switches (each run twice, with and without the filter, every frame rendered and
# read): without the filter seed 9 brings robots under 0.25 m in 4 of them (closest 15.0 cm), with it in
# none (34.1 cm); four switches would leave 3, the least the test accepts
@pytest.mark.parametrize("feedback, seed, switches", [("truth", 9, 12), ("truth", 24, 12), ("vision", 9, 5)])
def test_preset_swaps_keep_every_pair_apart(feedback, seed, switches, rig, gamma):
    s = _preset_swaps(seed, switches)
    cam = (rig, gamma) if feedback == "vision" else (None, None)
    off = _swaps(s.replace(safety=None), *cam)
    on = _swaps(s, *cam)
    print(f"\npreset_swaps, seed {seed}, {switches} switches, {feedback}: without the filter {off[0]} ticks under 0.25 m"
          f" in {off[1]} switches (closest {off[2] * 100:.1f} cm), settled error {off[3] * 100:.2f} cm; with it {on[0]}"
          f" ticks (closest {on[2] * 100:.1f} cm), settled error {on[3] * 100:.2f} cm")
    assert off[0] > 0 and off[1] >= 3  # the switches do bring robots together: the test can fail
    assert on[0] == 0 and on[2] >= 0.25
    assert on[3] <= 1.10 * off[3] + 0.002  # within 10 % (and 2 mm: both are a few mm)


@pytest.mark.parametrize("name", ["paper_simulation", "experiment1", "experiment2"])
def test_the_papers_runs_leave_the_filter_inactive_and_their_figures_unchanged(name):
    s = load_scenario(name)
    kernel = simulate(s)
    stepped = simulate_stepped(s.replace(safety=SafetySettings()))
    assert set(stepped.safety.status) == {"inactive"}
    rms = [float(np.sqrt(np.mean(np.linalg.norm(x.error, axis=-1) ** 2))) for x in (kernel, stepped.log)]
    assert rms[1] == pytest.approx(rms[0], rel=0.02)


def test_the_navigator_goes_round_a_wall_and_stops_at_the_goal():
    wall = np.column_stack([np.linspace(-0.8, 0.8, 33), np.full(33, 1.0)])  # across the way, 1 m ahead
    out = navigate(np.array([0.0, 3.0]), wall, 0.0, float("nan"), 1.0, np.zeros((0, 2)), 1.0, 1 / 30)
    assert not out.reached and abs(out.heading) > np.radians(30)  # it turns off the straight line
    assert navigate(np.array([0.0, 3.0]), np.zeros((0, 2)), 0.0, 0.0, 1.0, np.zeros((0, 2)), 1.0, 1 / 30).heading == 0.0
    done = navigate(np.array([0.01, 0.02]), wall, 0.0, 0.0, 1.0, np.zeros((0, 2)), 1.0, 1 / 30)
    assert done.reached and done.twist == (0.0, 0.0)
    boxed = np.array([[np.cos(a), np.sin(a)] for a in np.linspace(0, 2 * np.pi, 72, endpoint=False)]) * 0.5
    trapped = navigate(np.array([0.0, 3.0]), boxed, 0.0, 0.0, 1.0, np.zeros((0, 2)), 1.0, 1 / 30)
    assert trapped.blocked and trapped.twist == (0.0, 0.0)
    # the leader slows for a team that is behind, but never waits for ever
    slow = navigate(np.array([0.0, 3.0]), np.zeros((0, 2)), 0.5, 0.0, 1.0, np.zeros((0, 2)), 1.0, 1 / 30)
    assert 0.0 < slow.twist[0] <= NavSettings().creep * NavSettings().speed_mps + 1e-12
