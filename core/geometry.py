"""Angles and frame changes shared by the controller, simulator and vision.

Frames (see docs/paper-notes.md): the leader frame has x to the right, y forward; a
follower's heading ``a`` is measured in the leader frame from +x, so 90° means
aligned with the leader. The world frame has x east, y north; the leader's
world heading ``theta`` is measured from +x, so a leader heading north has
``theta = pi/2`` and then its frame coincides with the world axes.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from core.jit import kernel, ufunc

FloatArray = NDArray[np.float64]


def wrap_scalar(angle: float) -> float:
    """Wrap one angle (rad) to the half-open interval (-pi, pi], in plain Python (cheaper
    than a ufunc call for one number); :func:`wrap_angle` is this, compiled to a ufunc."""
    w = (angle + math.pi) % (2.0 * math.pi)  # Python semantics: in [0, 2 pi)
    if w == 0.0:
        w = 2.0 * math.pi
    return w - math.pi


wrap_angle = ufunc("float64(float64)")(wrap_scalar)
wrap_angle.__doc__ = "Wrap angles (rad) to the half-open interval (-pi, pi]; a ufunc, usable in kernels."  # type: ignore[misc]  # numba ufuncs take a docstring; numpy stubs call it read-only


def frame_yaw(leader_theta: ArrayLike) -> FloatArray:
    """Yaw of the leader frame's axes in the world: theta - pi/2 (x right, y forward)."""
    return np.asarray(leader_theta, dtype=np.float64) - np.pi / 2.0


@kernel
def world_to_leader_kernel(
    points: FloatArray, leader_x: float, leader_y: float, leader_theta: float, out: FloatArray
) -> None:
    """World points (m, 2) -> leader frame, into out: R(-phi) (p - p_leader), phi = theta - pi/2."""
    phi = leader_theta - 0.5 * math.pi
    c = math.cos(phi)
    s = math.sin(phi)
    for i in range(points.shape[0]):
        dx = points[i, 0] - leader_x
        dy = points[i, 1] - leader_y
        out[i, 0] = c * dx + s * dy
        out[i, 1] = -s * dx + c * dy


def world_to_leader(
    points_world: ArrayLike, leader_xy: ArrayLike, leader_theta: float
) -> FloatArray:
    """World points (n, 2) -> leader-frame points (n, 2): R(-phi) (p - p_leader)."""
    p = np.ascontiguousarray(np.atleast_2d(np.asarray(points_world, dtype=np.float64)))
    lxy = np.asarray(leader_xy, dtype=np.float64)
    out = np.empty_like(p)
    world_to_leader_kernel(p, float(lxy[0]), float(lxy[1]), float(leader_theta), out)
    return out


def leader_to_world(
    points_leader: ArrayLike, leader_xy: ArrayLike, leader_theta: float
) -> FloatArray:
    """Leader-frame points (n, 2) -> world points (n, 2): p_leader_origin + R(phi) p."""
    p = np.atleast_2d(np.asarray(points_leader, dtype=np.float64))
    phi = float(frame_yaw(leader_theta))
    c, s = np.cos(phi), np.sin(phi)
    rotated = np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], axis=1)
    return rotated + np.asarray(leader_xy, dtype=np.float64)


def heading_world_to_leader(theta_world: ArrayLike, leader_theta: float) -> FloatArray:
    """World headings -> leader-frame headings a (rad, wrapped); aligned = pi/2."""
    return wrap_angle(np.asarray(theta_world, dtype=np.float64) - frame_yaw(leader_theta))


def heading_leader_to_world(a_leader: ArrayLike, leader_theta: float) -> FloatArray:
    """Leader-frame headings a -> world headings (rad, wrapped)."""
    return wrap_angle(np.asarray(a_leader, dtype=np.float64) + frame_yaw(leader_theta))


def reexpress_in_new_frame(
    points_old: ArrayLike, dx: float, dy: float, gamma: float
) -> FloatArray:
    """Eq. 38 with the sign pinned down: old leader-frame points seen from the new frame.

    The leader moved by (dx, dy), expressed in its OLD frame, and turned
    counter-clockwise by ``gamma``. A world-fixed point p0 then has new
    coordinates R(-gamma) (p0 - d). The paper prints R(+gamma), which matches
    only if gamma is measured clockwise (docs/paper-notes.md). Headings follow with
    a1 = alpha0 - gamma (see :func:`rotate_heading_into_new_frame`).
    """
    p = np.ascontiguousarray(np.atleast_2d(np.asarray(points_old, dtype=np.float64)))
    out = np.empty_like(p)
    _reexpress_kernel(p, float(dx), float(dy), float(gamma), out)
    return out


@kernel
def _reexpress_kernel(p: FloatArray, dx: float, dy: float, gamma: float, out: FloatArray) -> None:
    c = math.cos(gamma)
    s = math.sin(gamma)
    for i in range(p.shape[0]):
        d0 = p[i, 0] - dx
        d1 = p[i, 1] - dy
        out[i, 0] = c * d0 + s * d1
        out[i, 1] = -s * d0 + c * d1


def rotate_heading_into_new_frame(a_old: ArrayLike, gamma: float) -> FloatArray:
    """Heading seen from a leader frame turned by gamma (CCW): a1 = alpha0 - gamma (§3.3)."""
    return wrap_angle(np.asarray(a_old, dtype=np.float64) - gamma)


def pose_floats(pose: ArrayLike) -> tuple[float, float, float]:
    """A pose (x, y, theta) as three Python floats, for scalar arithmetic and kernel arguments."""
    x, y, theta = np.asarray(pose, dtype=np.float64)[:3].tolist()
    return x, y, theta


def leader_displacement(
    pose_from: ArrayLike, pose_to: ArrayLike
) -> tuple[float, float, float]:
    """Leader odometry (dx, dy, gamma) between two world poses (x, y, theta), in the old frame."""
    x0, y0, t0 = pose_floats(pose_from)
    x1, y1, t1 = pose_floats(pose_to)
    phi = t0 - 0.5 * math.pi  # as world_to_leader_kernel
    c, s = math.cos(phi), math.sin(phi)
    ddx, ddy = x1 - x0, y1 - y0
    return c * ddx + s * ddy, -s * ddx + c * ddy, wrap_scalar(t1 - t0)
