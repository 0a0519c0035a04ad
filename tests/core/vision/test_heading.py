"""Headings: RANSAC line (§3.2), the arc of eq. 34-37 with eq. 38, the Kalman filter on a."""

import math
import numpy as np
import pytest
from core.geometry import heading_world_to_leader, leader_displacement, world_to_leader, wrap_angle
from core.sim.team import integrate_unicycle
from core.vision.heading import ArcAnchor, HeadingBank, arc_measurement, arc_measurements, chord_heading, fit_heading_line, min_displacement


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
