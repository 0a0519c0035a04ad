"""The free-space scan against the simulator's truth: box obstacles at the right distance,
nothing on the followers or the leader's body, and a memory that keeps what goes out of
sight (leader odometry, eq. 38) and forgets what the scan now sees as floor."""

from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np
import pytest

from core.camera.render import Renderer
from core.geometry import leader_displacement
from core.obstacles import Obstacle, ray_ranges
from core.sim.stepped import scan_settings_for
from core.control.safety import SafetySettings, obstacle_rows
from core.vision.freespace import FreeSpaceScanner, ObstacleMemory, Scan


@pytest.fixture(scope="module")
def scanner(rig, gamma):
    return FreeSpaceScanner(gamma, rig.working_area, scan_settings_for(rig))


def _truth(renderer: Renderer, leader: np.ndarray, followers: np.ndarray, bearings: np.ndarray) -> np.ndarray:
    """Ranges (leader frame) to the boxes drawn that are not followers, per bearing."""
    bx = renderer.boxes(leader, followers, clutter_only=True)
    boxes = np.column_stack([bx.x, bx.y, bx.a, bx.dims[:, 0] / 2, bx.dims[:, 1] / 2])
    return ray_ranges((0.0, 0.0), bearings + math.pi / 2, boxes)


def _random_world(rng: np.random.Generator, n_boxes: int) -> tuple[tuple[Obstacle, ...], np.ndarray]:
    """Boxes inside the working ring around a leader at the origin facing +y, and three
    followers clear of them."""
    boxes: list[Obstacle] = []
    while len(boxes) < n_boxes:
        r, b = rng.uniform(0.7, 1.9), rng.uniform(-math.pi, math.pi)
        o = Obstacle(-r * math.sin(b), r * math.cos(b), rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.5),
                     rng.uniform(-math.pi, math.pi), rng.uniform(0.15, 0.5))
        if all(math.dist((o.x, o.y), (q.x, q.y)) > 0.9 for q in boxes):
            boxes.append(o)
    followers: list[tuple[float, float, float]] = []
    while len(followers) < 3:
        r, b = rng.uniform(0.5, 1.7), rng.uniform(-math.pi, math.pi)
        x, y = -r * math.sin(b), r * math.cos(b)
        if all(math.dist((x, y), (o.x, o.y)) > 0.75 for o in boxes) and all(math.dist((x, y), f[:2]) > 0.45 for f in followers):
            followers.append((x, y, rng.uniform(-math.pi, math.pi)))
    return tuple(boxes), np.array(followers)


def test_box_obstacles_are_found_within_5_cm_of_the_truth(rig, scanner):
    rng = np.random.default_rng(21)
    errors, found, expected = [], 0, 0
    leader = np.array([0.0, 0.0, math.pi / 2])
    for k in range(60):
        boxes, followers = _random_world(rng, 3)
        renderer = Renderer(rig.model, replace(rig.render, clutter=False, distractor=False), boxes)
        frame = renderer.render(leader, followers, 0.7 * k, rng)
        estimate = followers[:, :2] + rng.normal(0.0, 0.01, (3, 2))  # the pipeline's estimates are this good
        scan = scanner.scan(frame, estimate, np.ones(3, dtype=bool))
        truth = _truth(renderer, leader, followers, scan.bearings)
        inside = np.isfinite(truth) & (truth > scan.min_range_m + 0.05) & (truth < scan.reach - 0.05) & ~scan.hidden
        expected += int(inside.sum())
        found += int(np.isfinite(scan.ranges[inside]).sum())
        errors.extend(np.abs(scan.ranges[inside] - truth[inside])[np.isfinite(scan.ranges[inside])])
    err = np.array(errors)
    print(f"\nscan vs truth: {found} of {expected} bearings with a box found; median error {np.median(err) * 100:.1f} cm,"
          f" p90 {np.percentile(err, 90) * 100:.1f} cm")
    assert expected > 1000 and found >= 0.95 * expected
    assert np.median(err) <= 0.05


def test_no_phantom_obstacle_on_a_follower_or_the_leaders_body_in_1000_frames(rig, scanner):
    """Followers anywhere in the ring (estimates 1 cm off), the leader anywhere on the tiled
    floor under drifting light, no obstacle: the scan must see nothing at all."""
    renderer = Renderer(rig.model, replace(rig.render, clutter=False, distractor=False))
    rng = np.random.default_rng(4)
    hits = 0
    for _ in range(1000):
        leader = np.array([rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)])
        n = int(rng.integers(1, 7))
        r, b = rng.uniform(0.45, 1.8, n), rng.uniform(-math.pi, math.pi, n)
        followers = np.column_stack([-r * np.sin(b), r * np.cos(b), rng.uniform(-math.pi, math.pi, n)])
        frame = renderer.render(leader, followers, rng.uniform(0, 60), rng)
        scan = scanner.scan(frame, followers[:, :2] + rng.normal(0.0, 0.01, (n, 2)), np.ones(n, dtype=bool))
        hits += int(np.isfinite(scan.ranges).sum())
    assert hits == 0


def _scan_with(points: dict[int, float], scanner: FreeSpaceScanner, hidden: tuple[int, ...] = ()) -> Scan:
    ranges = np.full(scanner.bin_bearings.shape[0], np.inf)
    for b, r in points.items():
        ranges[b] = r
    mask = np.zeros_like(ranges, dtype=bool)
    mask[list(hidden)] = True
    return Scan(scanner.bin_bearings, ranges, scanner.bin_reach, mask, scanner.min_range_m)


def test_the_memory_keeps_what_leaves_the_ring_or_hides_and_forgets_what_is_seen_free(scanner):
    memory = ObstacleMemory(scanner.settings)
    ahead = 180  # the bin straight ahead (bearing 0)
    pts = memory.update(_scan_with({ahead: 1.0}, scanner), 0.0)
    assert len(pts) == 1 and np.allclose(pts[0], [0.0, 1.0], atol=0.02)
    # the leader turns by 180 degrees on the spot: the obstacle is now behind it, still 1 m away
    memory.move(leader_displacement((0.0, 0.0, math.pi / 2), (0.0, 0.0, -math.pi / 2)))
    assert np.allclose(memory.current(0.5), [[0.0, -1.0]], atol=0.02)  # between scans: moved by the odometry
    hidden = tuple(range(0, 5)) + tuple(range(355, 360))  # a follower hides what is straight behind
    pts = memory.update(_scan_with({}, scanner, hidden), 1.0)
    assert len(pts) == 1 and np.allclose(pts[0], [0.0, -1.0], atol=0.02)
    # seen as floor now (the follower moved away): forgotten at once
    assert len(memory.update(_scan_with({}, scanner), 1.1)) == 0
    # drive 4 m away from a remembered point: out of the ring, kept for keep_s, then forgotten
    memory.update(_scan_with({ahead: 1.0}, scanner), 2.0)
    memory.move((0.0, -4.0, 0.0))  # backwards: the point is now 5 m ahead, beyond the ring
    assert np.allclose(memory.update(_scan_with({}, scanner), 3.0), [[0.0, 5.0]], atol=0.02)
    assert len(memory.update(_scan_with({}, scanner), 2.0 + scanner.settings.keep_s + 0.1)) == 0


def test_the_filter_gets_the_nearest_point_per_direction_around_each_robot():
    wall = np.column_stack([np.linspace(-1, 1, 81), np.full(81, 0.5)])
    picked = obstacle_rows(wall, np.array([[0.0, 0.2]]), SafetySettings())
    assert 1 <= len(picked) <= 8 and np.all(picked[:, 2] == 0.0)
    assert np.allclose(picked[np.argmin(np.hypot(*(picked[:, :2] - [0.0, 0.2]).T)), :2], [0.0, 0.5])
    assert len(obstacle_rows(wall, np.array([[0.0, -2.0]]), SafetySettings())) == 0


def test_the_scan_looks_only_at_the_ring_and_sees_what_the_whole_frame_shows(rig, scanner):
    """A frame that makes its pixels when looked at makes only the working ring's square for
    the scan (about half the frame), and the polar grid it samples there is the whole frame's,
    sample for sample, also where the grid leaves the image."""
    rng = np.random.default_rng(5)
    renderer = Renderer(rig.model, rig.render)
    leader = np.array([0.0, 0.0, math.pi / 2])
    followers = np.array([[0.6, 0.9, 0.3], [-0.8, 0.4, 1.0], [0.1, -1.2, 2.0]])
    h, w = rig.model.height, rig.model.width
    for k in range(3):
        lazy = renderer.frame(leader, followers, 0.5 * k, rng)
        scan = scanner.scan(lazy, followers[:, :2], np.ones(3, bool))
        assert 0 < lazy.pixels_rendered <= 0.55 * h * w
        again = scanner.scan(np.asarray(lazy), followers[:, :2], np.ones(3, bool))  # the whole frame, the same pixels
        assert np.array_equal(scan.ranges, again.ranges) and np.array_equal(scan.hidden, again.hidden)
    frame = np.asarray(renderer.frame(leader, followers, 0.0, rng))
    for shape in ((h, w), (200, 260), (h + 40, w + 40), (100, 100)):  # the ring inside, cut by, beyond, outside
        img = np.zeros((*shape, 3), np.uint8)
        img[:min(h, shape[0]), :min(w, shape[1])] = frame[:shape[0], :shape[1]]
        full = cv2.remap(img, scanner.map_x, scanner.map_y, cv2.INTER_NEAREST, borderValue=(0, 0, 0))
        rows, cols, map_x, map_y = scanner._crop(img.shape)
        assert np.array_equal(cv2.remap(img[rows, cols], map_x, map_y, cv2.INTER_NEAREST, borderValue=(0, 0, 0)), full)


def test_the_floor_model_is_the_medians_and_mads_numpy_gives():
    """The floor's colour and spread come from counts (core.vision.freespace.floor_model): the
    very medians and median absolute deviations of the sampled features that numpy computes, on
    random images, a near-uniform floor, a single colour and every sampling step."""
    from core.vision.freespace import floor_model

    rng = np.random.default_rng(7)
    for trial in range(120):
        h, w = (int(v) for v in rng.integers(1, 50, 2))
        kind = trial % 3
        if kind == 0:
            img = rng.integers(0, 256, (h, w, 3))
        elif kind == 1:
            img = np.clip(rng.normal(120, 8, (h, w, 3)), 0, 255)
        else:
            img = np.full((h, w, 3), rng.integers(0, 256, 3))
        img = img.astype(np.uint8)
        step = int(rng.integers(1, 5))
        x = img[::step, ::step].reshape(-1, 3).astype(np.float64)
        feats = np.column_stack([(x[:, 0] + x[:, 1] + x[:, 2]) / 3, x[:, 2] - x[:, 1], x[:, 0] - x[:, 1]])
        med = np.median(feats, axis=0)
        mad = np.median(np.abs(feats - med), axis=0)
        got = floor_model(img, step)
        np.testing.assert_allclose(got[:3], med, atol=1e-9)
        np.testing.assert_allclose(got[3:], mad, atol=1e-9)


def test_a_scan_taken_into_the_memory_after_the_leader_moved_counts_from_its_frames_pose():
    """A scan finished a tick after its frame (the live loop's second half) goes into the memory
    as of the pose the leader had at that frame: the same points as had it gone in before the move."""
    bearings = -np.pi + (np.arange(360) + 0.5) * np.pi / 180
    ranges = np.full(360, np.inf)
    ranges[100:110] = 0.9
    ranges[250:255] = 1.4
    scan = Scan(bearings, ranges, np.full(360, 2.0), np.zeros(360, dtype=bool), 0.28)
    then, later = ObstacleMemory(), ObstacleMemory()
    then.update(scan, 1.0)
    then.move((0.02, 0.01, 0.03))
    pose = later.pose
    later.move((0.02, 0.01, 0.03))
    later.update(scan, 1.0, pose=pose)
    assert np.allclose(np.sort(then.points, axis=0), np.sort(later.points, axis=0))
    assert np.allclose(np.sort(then.current(1.1), axis=0), np.sort(later.current(1.1), axis=0))
    wrong = ObstacleMemory()
    wrong.move((0.02, 0.01, 0.03))
    wrong.update(scan, 1.0)  # as though the frame were the newest: 2 cm and 1.7 degrees off
    assert np.hypot(*(then.points.mean(axis=0) - wrong.points.mean(axis=0))) > 0.01
