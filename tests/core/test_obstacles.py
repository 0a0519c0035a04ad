"""Obstacles: exact box geometry (distance, nearest point, rays) and their place in a scenario
file, with one line for each bad value."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from core.config import ConfigError, parse_scenario
from core.obstacles import Obstacle, as_array, nearest_points, ray_ranges, surface_distance
from tests.helpers import SCENARIOS

BOX = as_array([Obstacle(1.0, 2.0, 0.8, 0.4, math.radians(30.0))])


def test_distance_nearest_point_and_ray_agree_on_a_turned_box():
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    face = np.array([1.0, 2.0]) + 0.6 * np.array([c, s])  # 0.2 m beyond the end face, on the long axis
    assert surface_distance(face[None], BOX)[0, 0] == pytest.approx(0.2)
    assert surface_distance(np.array([[1.0, 2.0]]), BOX)[0, 0] == pytest.approx(-0.2)  # inside: to the long side
    near = nearest_points(face[None], BOX)[0, 0]
    assert np.allclose(near, np.array([1.0, 2.0]) + 0.4 * np.array([c, s]))
    # a ray from 3 m out along the long axis meets the end face 2.6 m away; one beside the box misses
    origin = (1.0 + 3.0 * c, 2.0 + 3.0 * s)
    hit, miss = ray_ranges(origin, np.array([math.radians(210.0), math.radians(150.0)]), BOX, max_range=10.0)
    assert hit == pytest.approx(2.6) and miss == 10.0


@settings(max_examples=200, deadline=None)
@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(-math.pi, math.pi))
def test_a_ray_stops_where_the_surface_is(x, y, direction):
    """Where a ray meets the box, that point is on the surface (distance 0), and every point
    of the ray before it is outside."""
    r = ray_ranges((x, y), np.array([direction]), BOX)[0]
    inside = surface_distance(np.array([[x, y]]), BOX)[0, 0] < 0
    if inside:
        assert r == 0.0
    elif math.isfinite(r):
        hit = np.array([[x + r * math.cos(direction), y + r * math.sin(direction)]])
        assert abs(surface_distance(hit, BOX)[0, 0]) < 1e-9
        before = np.array([[x + t * r * math.cos(direction), y + t * r * math.sin(direction)] for t in (0.2, 0.6, 0.95)])
        assert np.all(surface_distance(before, BOX) > 0)


def _scenario(extra: str) -> str:
    return (SCENARIOS / "narrow_gap.toml").read_text() + extra


@pytest.mark.parametrize("extra, expected", [
    ('\n[[obstacles]]\ncenter = [2.0, 2.0]\nsize = [0.0, 0.4]\n', "size = [0.0, 0.4]: must be [length, width] in (0, 5] m"),
    ('\n[[obstacles]]\ncenter = [2.0, 2.0]\nsize = [nan, 0.4]\n', "must be [length, width] in (0, 5] m"),
    ('\n[[obstacles]]\ncenter = [20.0, 2.0]\nsize = [0.4, 0.4]\n', "center = [20.0, 2.0]: must be [x, y] with |x|, |y| <= 10 m"),
    ('\n[[obstacles]]\ncenter = [0.0, 0.1]\nsize = [0.4, 0.4]\n', "clear of the leader"),
    ('\n[[obstacles]]\ncenter = [-0.6, -0.8]\nsize = [0.4, 0.4]\n', "clear of the robots: follower 1 starts 0 cm from its surface"),
    ('\n[[obstacles]]\ncenter = [0.0, 5.1]\nsize = [0.4, 0.4]\n', "clear of the leader's goal"),
    ('\n[[obstacles]]\ncenter = [2.0, 2.0]\nsize = [0.4, 0.4]\nheight_m = -1\n', "height_m = -1: must be a number in (0, 2] m"),
    ('\n[[obstacles]]\ncenter = [2.0, 2.0]\nsize = [0.4, 0.4]\ncolour = "red"\n', "obstacles[3].colour is not a known key"),
])
def test_bad_obstacles_are_refused_in_one_line(extra, expected):
    with pytest.raises(ConfigError) as err:
        parse_scenario(_scenario(extra), "narrow_gap.toml")
    message = str(err.value)
    assert expected in message and "\n" not in message and message.startswith("narrow_gap.toml: ")


@pytest.mark.parametrize("old, new, expected", [
    ("[safety]\nmin_distance_m = 0.25", "[safety]\nmin_distance_m = 5.0", "safety.min_distance_m = 5.0: must be a number in [0.15, 1] m"),
    ("[safety]\nmin_distance_m = 0.25", "[safety]\nenabled = 1", "safety.enabled = 1: must be true or false"),
    ("min_scale = 0.3", "min_scale = 0.0", "formation.min_scale = 0.0: must be a number in [0.3, 1]"),
    ('goal = [0.0, 5.0]', 'goal = [0.0, "far"]', "leader.goal = [0.0, 'far']: must be [x, y]"),
])
def test_bad_safety_and_goal_values_are_refused_in_one_line(old, new, expected):
    text = (SCENARIOS / "narrow_gap.toml").read_text()
    assert old in text
    with pytest.raises(ConfigError) as err:
        parse_scenario(text.replace(old, new), "narrow_gap.toml")
    assert expected in str(err.value)


def test_switches_are_listed_or_drawn_but_not_both():
    text = (SCENARIOS / "preset_swaps.toml").read_text()
    s = parse_scenario(text, "p")
    assert len(s.switches) == 100 and all(b[0] - a[0] == pytest.approx(20.0) for a, b in zip(s.switches, s.switches[1:]))
    assert parse_scenario(text, "p").switches[7][1].tolist() == s.switches[7][1].tolist()  # seeded
    listed = text.replace("switch_every_s = 20.0", '[[formation.switches]]\nat_s = 5.0\npreset = "column"\n')
    assert len(parse_scenario(listed, "p").switches) == 1
    with pytest.raises(ConfigError, match="one or the other"):
        parse_scenario(text.replace("switch_every_s = 20.0", 'switch_every_s = 20.0\n[[formation.switches]]\nat_s = 5.0\npreset = "V"'), "p")
    with pytest.raises(ConfigError, match="preset = 'star': must be one of"):
        parse_scenario(listed.replace('"column"', '"star"'), "p")
