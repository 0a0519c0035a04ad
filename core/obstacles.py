"""Obstacles on the floor: boxes fixed in the world, and what any point or ray makes of them.

A scenario names its obstacles in the world frame, which is the leader frame at t = 0 (the
leader starts at the origin facing +y, as the paper's figures do), so they are written as
the followers' starting positions are. Everything here is exact geometry of oriented
rectangles (a box's footprint): signed distance from a point, the nearest point of the
surface, and the first hit of a ray. The simulator uses it as the truth; the safety filter
uses the nearest points when the feedback is the simulator's truth, and the free-space
scan is checked against ``ray_ranges``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.types import FloatArray


@dataclass(frozen=True)
class Obstacle:
    """A box standing on the floor: centre (x, y) and heading (rad, of its length from +x) in
    the world frame; footprint length × width and height (m)."""

    x: float
    y: float
    length: float
    width: float
    heading: float = 0.0
    height: float = 0.3


def as_array(obstacles: tuple[Obstacle, ...] | list[Obstacle]) -> FloatArray:
    """(m, 5) rows x, y, heading, half length, half width."""
    if not obstacles:
        return np.zeros((0, 5))
    return np.array([[o.x, o.y, o.heading, o.length / 2, o.width / 2] for o in obstacles], dtype=np.float64)


def _local(points: FloatArray, boxes: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Points (k, 2) in each box's own frame: (k, m) along and across."""
    dx = points[:, None, 0] - boxes[None, :, 0]
    dy = points[:, None, 1] - boxes[None, :, 1]
    c, s = np.cos(boxes[:, 2]), np.sin(boxes[:, 2])
    return c * dx + s * dy, -s * dx + c * dy


def surface_distance(points: FloatArray, boxes: FloatArray) -> FloatArray:
    """(k, m) distance from each point to each box's footprint; negative inside it."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if boxes.shape[0] == 0:
        return np.zeros((p.shape[0], 0))
    u, w = _local(p, boxes)
    qu, qw = np.abs(u) - boxes[:, 3], np.abs(w) - boxes[:, 4]
    outside = np.hypot(np.maximum(qu, 0.0), np.maximum(qw, 0.0))
    inside = np.minimum(np.maximum(qu, qw), 0.0)
    return np.asarray(outside + inside)


def nearest_points(points: FloatArray, boxes: FloatArray) -> FloatArray:
    """(k, m, 2) the point of each box's footprint nearest to each point (the point itself inside)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if boxes.shape[0] == 0:
        return np.zeros((p.shape[0], 0, 2))
    u, w = _local(p, boxes)
    u = np.clip(u, -boxes[:, 3], boxes[:, 3])
    w = np.clip(w, -boxes[:, 4], boxes[:, 4])
    c, s = np.cos(boxes[:, 2]), np.sin(boxes[:, 2])
    return np.stack([boxes[:, 0] + c * u - s * w, boxes[:, 1] + s * u + c * w], axis=-1)


def ray_ranges(origin: tuple[float, float], directions: FloatArray, boxes: FloatArray,
               max_range: float = math.inf) -> FloatArray:
    """(r,) distance along each ray (world angles, rad) from ``origin`` to the first box it
    meets (slab method on each box's frame); ``max_range`` where it meets none."""
    ang = np.asarray(directions, dtype=np.float64).reshape(-1)
    out = np.full(ang.shape, float(max_range))
    if boxes.shape[0] == 0:
        return out
    o = np.array([origin], dtype=np.float64)
    u0, w0 = _local(o, boxes)  # (1, m)
    rel = ang[:, None] - boxes[None, :, 2]
    du, dw = np.cos(rel), np.sin(rel)  # (r, m) the rays' directions in each box's frame
    with np.errstate(divide="ignore", invalid="ignore"):
        t1u, t2u = (-boxes[:, 3] - u0) / du, (boxes[:, 3] - u0) / du
        t1w, t2w = (-boxes[:, 4] - w0) / dw, (boxes[:, 4] - w0) / dw
    # a ray parallel to a slab: inside it for every t, or never
    inside_u = np.abs(u0) <= boxes[:, 3]
    inside_w = np.abs(w0) <= boxes[:, 4]
    near_u = np.where(du == 0, np.where(inside_u, -np.inf, np.inf), np.minimum(t1u, t2u))
    far_u = np.where(du == 0, np.where(inside_u, np.inf, -np.inf), np.maximum(t1u, t2u))
    near_w = np.where(dw == 0, np.where(inside_w, -np.inf, np.inf), np.minimum(t1w, t2w))
    far_w = np.where(dw == 0, np.where(inside_w, np.inf, -np.inf), np.maximum(t1w, t2w))
    t_in = np.maximum(np.maximum(near_u, near_w), 0.0)
    t_out = np.minimum(far_u, far_w)
    hit = t_in <= t_out
    first = np.where(hit, t_in, np.inf).min(axis=1)
    return np.asarray(np.minimum(out, first))


def seen_from(boxes: FloatArray, leader_pose: FloatArray, robots: FloatArray) -> FloatArray:
    """What the simulator's truth tells the leader of the boxes (world rows of ``as_array``):
    for each robot (leader frame, (k, 2); the leader itself is added at the origin) the
    nearest point of each box, in the leader frame (m·(k + 1), 2)."""
    if boxes.shape[0] == 0:
        return np.zeros((0, 2))
    x, y, theta = (float(v) for v in np.asarray(leader_pose, dtype=np.float64)[:3])
    phi = theta - math.pi / 2
    c, s = math.cos(phi), math.sin(phi)
    dx, dy = boxes[:, 0] - x, boxes[:, 1] - y
    local = np.column_stack([c * dx + s * dy, -s * dx + c * dy, boxes[:, 2] - phi, boxes[:, 3:]])
    pts = np.vstack([np.zeros((1, 2)), np.asarray(robots, dtype=np.float64).reshape(-1, 2)])
    return nearest_points(pts, local).reshape(-1, 2)
