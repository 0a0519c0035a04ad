"""Markers that never merge silently: two followers whose marker hues are 15 deg apart,
one behind the other along a bearing, are two followers, both tracked where they are; a
team whose hues are closer than the documented minimum is refused by the config."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from core.camera.config import MIN_HUE_SEPARATION_DEG, parse_camera
from core.camera.render.looks import marker_bgr
from core.config import ConfigError, parse_scenario
from core.sim.profiles import ConstantProfile
from core.sim.stepped import simulate_stepped
from core.vision.blobs import DetectSettings, find_blobs, hue_distance_deg

from tests.helpers import SCENARIOS


@pytest.mark.parametrize("gap_m, bearing_deg", [(0.3, 30.0), (0.45, 135.0), (0.6, 250.0), (0.3, 340.0)])
def test_two_markers_15_deg_apart_one_behind_the_other_are_two_tracked_followers(rig, gamma, gap_m, bearing_deg):
    two = dataclasses.replace(rig, render=dataclasses.replace(rig.render, hues_deg=(0.0, 15.0, 240.0)))
    b, near = math.radians(bearing_deg), 0.8
    p = np.array([[near * math.sin(b), near * math.cos(b)],
                  [(near + gap_m) * math.sin(b), (near + gap_m) * math.cos(b)]])
    base = parse_scenario((SCENARIOS / "experiment1.toml").read_text(), "experiment1.toml")
    sc = base.replace(initial_p=p, initial_a=np.full(2, math.pi / 2), slots=p.copy(),
                      leader=ConstantProfile(0.06, 0.0), duration_s=10.0, disturbances=())
    v = simulate_stepped(sc, two, gamma).vision
    assert v is not None
    after = v.log.t >= 0
    assert v.tracked[after].all(), "both followers tracked throughout"
    err = np.linalg.norm(v.log.p_meas[after] - v.log.p[after], axis=-1)
    assert err.max() < 0.03, err.max(axis=0)  # each where it is: not both on one marker
    assert hue_distance_deg(v.hues_deg[-1, 0], v.hues_deg[-1, 1]) > 8.0  # two colours learned, not one blend


def _marker(img, x, y, hue):
    b, g, r = marker_bgr(hue, 0.85, 0.85)
    cv2.rectangle(img, (x, y), (x + 14, y + 8), (int(b), int(g), int(r)), -1)


def test_touching_markers_of_two_known_hues_are_two_blobs():
    img = np.full((120, 120, 3), 128, np.uint8)
    _marker(img, 30, 40, 0.0)
    _marker(img, 30, 50, 15.0)  # right behind it, 2 px apart
    assert len(find_blobs(img, None, DetectSettings(), known_hues=(0.0, 15.0))) == 2
    # pieces of one rectangle (the same hue, cut by a reflection) still merge
    img2 = np.full((120, 120, 3), 128, np.uint8)
    _marker(img2, 30, 40, 0.0)
    _marker(img2, 30, 52, 2.0)
    assert len(find_blobs(img2, None, DetectSettings(), known_hues=(0.0, 120.0))) == 1


def test_a_team_with_hues_closer_than_the_minimum_is_refused():
    head = "[working_area]\ninner_px = 55\nouter_px = 195\n"
    with pytest.raises(ConfigError, match=rf"render.hues_deg: markers 1 and 2 have hues 0 and 10 deg, 10 deg apart;"
                                          rf" two markers need at least {MIN_HUE_SEPARATION_DEG:g} deg"):
        parse_camera(head + "[render]\nhues_deg = [0, 10, 240]\n", "cam.toml")
    with pytest.raises(ConfigError, match="markers 1 and 3"):
        parse_camera(head + "[render]\nhues_deg = [355, 120, 5]\n", "cam.toml")  # across 0: 10 deg apart
    parse_camera(head + f"[render]\nhues_deg = [0, {MIN_HUE_SEPARATION_DEG:g}, 240]\n", "cam.toml")
    with pytest.raises(ConfigError, match="detect.merge_hue_deg = 20"):
        parse_camera(head + "[detect]\nmerge_hue_deg = 20\n", "cam.toml")
