"""The vision pipeline, stage by stage on synthetic frames with known truth, then closed loop."""

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from core.camera.config import DetectSettings, parse_camera
from core.camera.render import Renderer
from core.geometry import heading_world_to_leader, leader_displacement, world_to_leader, wrap_angle
from core.sim.team import integrate_unicycle, make_team_state, step_team
from core.types import Commands
from core.vision.blobs import hue_distance_deg
from core.vision.heading import ArcAnchor, HeadingBank, arc_measurement, arc_measurements, chord_heading, fit_heading_line, min_displacement
from core.vision.pipeline import VisionPipeline
from core.vision.tracking import back_projection, hue_histogram, hue_lookup

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def rig():
    return parse_camera((ROOT / "static_config/camera/synthetic.toml").read_text(), "synthetic.toml")


@pytest.fixture(scope="module")
def gamma():
    path = ROOT / "static_config/camera/synthetic_calibrated.toml"
    return parse_camera(path.read_text(), path.name).gamma


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


def test_ransac_heading_within_5_degrees_with_20_percent_outliers():
    rng = np.random.default_rng(7)
    for trial in range(50):
        heading = rng.uniform(-math.pi, math.pi)
        s = np.linspace(0, 0.12, 40)
        pts = np.array([0.3, -0.5]) + np.outer(s, [math.cos(heading), math.sin(heading)])
        pts += rng.normal(0, 0.002, pts.shape)
        bad = rng.choice(40, 8, replace=False)
        normal = np.array([-math.sin(heading), math.cos(heading)])
        off = rng.uniform(0.02, 0.08, 8) * rng.choice([-1, 1], 8)  # 2..8 cm off the line, either side
        pts[bad] += off[:, None] * normal + rng.uniform(-0.03, 0.03, (8, 1)) * normal[::-1] * [1, -1]
        fit = fit_heading_line(pts, rng)
        assert abs(math.degrees(wrap_angle(fit.heading - heading))) < 5.0, trial
        assert not fit.inliers[bad].any()


def test_eq34_to_37_heading_on_a_clean_arc_and_a_straight_line():
    for w in (0.0, 0.4, -1.0, 2.0):
        pose = np.array([0.2, -0.4, 1.1])
        dt = 0.3
        end = integrate_unicycle(pose, 0.1, w, dt)[0]
        a = chord_heading(pose[:2], end[:2], w * dt)
        assert abs(math.degrees(wrap_angle(a - end[2]))) < 3.0 * 0.01  # exact up to rounding
    # the paper's special case x2 = x1
    assert chord_heading([0.0, 0.0], [0.0, 0.05], 0.0) == pytest.approx(math.pi / 2)
    assert chord_heading([0.0, 0.05], [0.0, 0.0], 0.0) == pytest.approx(-math.pi / 2)
    assert min_displacement(0.0) == pytest.approx(0.02) and min_displacement(10.0) == pytest.approx(0.05)


def test_arc_measurement_with_the_leader_moving_uses_eq38():
    """A follower's arc seen from a leader that moved and turned: the anchor re-expressed by the
    leader's odometry, the chord and the turn give the follower's heading in the new frame."""
    leader0 = np.array([0.0, 0.0, math.pi / 2])
    follower0 = np.array([0.5, 0.3, 1.0])
    dt, steps = 1 / 30, 12
    leader, follower = leader0.copy(), follower0.copy()
    anchor = ArcAnchor(world_to_leader(follower0[:2], leader0[:2], leader0[2])[0])
    for _ in range(steps):
        new_leader = integrate_unicycle(leader, 0.06, 0.3, dt)[0]
        anchor.move_leader(*leader_displacement(leader, new_leader))
        anchor.add_command(0.1, 0.8, dt)
        follower = integrate_unicycle(follower, 0.1, 0.8, dt)[0]
        leader = new_leader
    pos = world_to_leader(follower[:2], leader[:2], leader[2])[0]
    z = arc_measurement(anchor, pos, 0.0)
    truth = float(heading_world_to_leader(follower[2], leader[2]))
    assert z is not None and abs(math.degrees(wrap_angle(z - truth))) < 0.01
    # too short a move gives no measurement (eq. 34)
    assert arc_measurement(ArcAnchor(pos - [0.005, 0.0]), pos, 0.0) is None


def test_kalman_heading_residual_wraps_around_pi():
    kf = HeadingBank(3, math.radians(10), math.radians(5))
    kf.start(1, math.radians(178.0), math.radians(5))
    one = np.array([1])
    for _ in range(5):
        kf.predict(np.zeros(3), 1 / 30)
        assert kf.update(one, np.array([math.radians(-178.0)]))[0]
    assert abs(math.degrees(wrap_angle(kf.headings[1] - math.pi))) < 2.5
    assert np.isnan(kf.headings[0]) and np.isnan(kf.headings[2])  # never started: untouched
    # a wild measurement is gated out, but a persistent one is believed
    assert not kf.update(one, np.array([0.0]))[0]
    assert not kf.update(one, np.array([0.0]))[0]
    assert kf.update(one, np.array([0.0]))[0]


def test_heading_bank_is_independent_filters_fused_together():
    """Filters of one bank do not interact: each matches a bank of its own, step for step."""
    rng = np.random.default_rng(4)
    together = HeadingBank(4, 0.1, 0.08)
    alone = [HeadingBank(1, 0.1, 0.08) for _ in range(4)]
    for i in range(4):
        together.start(i, 0.5 * i, 0.2 + 0.05 * i)
        alone[i].start(0, 0.5 * i, 0.2 + 0.05 * i)
    for _ in range(30):
        turns = rng.normal(0.0, 0.05, 4)
        together.predict(turns, 1 / 30)
        which = np.flatnonzero(rng.random(4) < 0.5)
        z = together.headings[which] + rng.normal(0.0, 0.1, len(which))
        together.update(which, z)
        for i in range(4):
            alone[i].predict(turns[i:i + 1], 1 / 30)
        for k, i in enumerate(which):
            alone[i].update(np.array([0]), z[k:k + 1])
    assert np.allclose(together.headings, [b.headings[0] for b in alone])
    assert np.allclose(together.sigmas, [b.sigmas[0] for b in alone])


def test_arc_measurements_match_one_at_a_time():
    rng = np.random.default_rng(5)
    anchors = rng.uniform(-1, 1, (6, 2))
    pos = anchors + rng.normal(0.0, 0.04, (6, 2))
    turns, travel, err = rng.normal(0, 0.2, 6), rng.normal(0, 0.1, 6), rng.uniform(0, 0.5, 6)
    z = arc_measurements(anchors, turns, travel, pos, err)
    for i in range(6):
        one = arc_measurement(ArcAnchor(anchors[i], float(turns[i]), float(travel[i])), pos[i], float(err[i]))
        assert (one is None and np.isnan(z[i])) or one == pytest.approx(z[i])


def every_colour() -> np.ndarray:
    """A 4096 x 4096 BGR image holding each of the 2^24 colours once."""
    c = np.arange(1 << 24, dtype=np.uint32).reshape(4096, 4096)
    return np.dstack([c & 255, (c >> 8) & 255, c >> 16]).astype(np.uint8)


def test_the_one_pass_back_projection_is_opencvs_hsv_on_every_colour():
    img = every_colour()
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)
    everywhere = np.full(img.shape[:2], 255, np.uint8)
    # a lookup that is the identity shows the hue byte itself
    hue = back_projection(img, np.arange(256, dtype=np.uint8), everywhere, DetectSettings(min_saturation=0, min_value=0))
    assert np.array_equal(hue, hsv[..., 0])
    # a lookup of all 255 shows which pixels pass the saturation and value floors
    for s_min, v_min in ((90, 50), (1, 0), (0, 255), (255, 1), (37, 201)):
        passed = back_projection(img, np.full(256, 255, np.uint8), everywhere,
                                 DetectSettings(min_saturation=s_min, min_value=v_min))
        assert np.array_equal(passed, cv2.inRange(hsv, (0, s_min, v_min), (180, 255, 255))), (s_min, v_min)


def test_the_one_pass_back_projection_is_the_opencv_chain_on_a_rendered_frame(rig):
    frame = Renderer(rig.model, rig.render).render(np.zeros(3), np.array([[0.0, 0.6, 1.0], [-0.5, 0.4, 2.0]]), 0.0,
                                                   np.random.default_rng(3))
    hsv = cv2.cvtColor(frame, cv2.COLOR_BGR2HSV)
    detect = rig.detect
    sat = cv2.inRange(hsv, (0, detect.min_saturation, detect.min_value), (180, 255, 255))
    area = np.zeros(frame.shape[:2], np.uint8)
    cv2.circle(area, (320, 240), 200, 255, -1)
    hist = hue_histogram(hsv, sat)
    chain = cv2.bitwise_and(cv2.bitwise_and(cv2.calcBackProject([hsv], [0], hist, [0, 180], 1), sat), area)
    assert chain.any()
    assert np.array_equal(back_projection(frame, hue_lookup(hist), area, detect), chain)
    # a region of the frame (a strided view, as a camera frame's ROI is) gives the same bytes
    view = frame[100:300, 150:420]
    assert not view.flags.c_contiguous
    assert np.array_equal(back_projection(view, hue_lookup(hist), area[100:300, 150:420], detect),
                          chain[100:300, 150:420])
