"""Formation controller of paper §2: pose controller (eq. 3-4), leader-motion
compensation (eq. 5-9, rigid-body form) and command generation (eq. 10-12).

Vectorised over n followers: positions (n, 2) m and headings (n,) rad in the
leader frame (x right, y forward, heading 90° = aligned). The per-follower
math lives in one compiled kernel (:func:`controller_kernel`) that both
:func:`compute_commands` (the live loop, per tick) and the whole-run simulator
call, so there is a single implementation.

Why the compensation is not written as eq. 6-9: taken literally (arctan,
v_i = w_l r_i) those equations are singular at w_l = 0 and at r + x_i = 0 and
have the wrong sign for w_l < 0. They describe the velocity of a point rigidly
attached to the leader frame, which is (-w_l y, v_l + w_l x) for every w_l;
:func:`compensation_velocity` is that form and
:func:`compensation_velocity_paper` keeps the literal one for comparison.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from core.control.limits import clamp_command
from core.geometry import wrap_angle
from core.jit import kernel, ufunc
from core.types import GAIN_INDEX, BoolArray, Commands, FloatArray, Gains, float_rows

# Below this reference speed (m/s) the reference angle a_r is undefined: it is held.
REFERENCE_SPEED_EPS = 1e-4

_K_F1, _K_F2, _A = GAIN_INDEX["k_f1"], GAIN_INDEX["k_f2"], GAIN_INDEX["a"]
_K_W1, _K_W2 = GAIN_INDEX["k_w1"], GAIN_INDEX["k_w2"]
_V_MAX, _W_MAX = GAIN_INDEX["v_max"], GAIN_INDEX["w_max"]
_ACC_V, _ACC_W, _TAU_AR = GAIN_INDEX["accel_v_max"], GAIN_INDEX["accel_w_max"], GAIN_INDEX["tau_ar"]


@ufunc("float64(float64, float64, float64, float64)")
def saturate_position_error(err: float, k_f1: float, k_f2: float, a: float) -> float:
    """Eq. 4, per component: f = (k_f1 + k_f2 tanh|e|) / (a + |e|) * e.

    |f| < k_f1 + k_f2 for every error; the small-error gain is k_f1 / a.
    """
    mag = abs(err)
    return (k_f1 + k_f2 * math.tanh(mag)) / (a + mag) * err


@ufunc("float64(float64, float64, float64)")
def heading_saturation(err: float, k_w1: float, k_w2: float) -> float:
    """Eq. 12: f(a~) = k_w1 tanh^3(k_w2 a~); odd, |f| < k_w1, flat near zero."""
    return k_w1 * math.tanh(k_w2 * err) ** 3


def pose_control(p: ArrayLike, p_d: ArrayLike, p_d_dot: ArrayLike, gains: Gains) -> FloatArray:
    """Eq. 3 with rho(xi) = xi (so J = I): xi_dot_fr = rho_dot_d + f(rho_d - rho), (n, 2) m/s."""
    err = np.asarray(p_d, dtype=np.float64) - np.asarray(p, dtype=np.float64)
    return np.asarray(p_d_dot, dtype=np.float64) + saturate_position_error(
        err, gains.k_f1, gains.k_f2, gains.a
    )


def compensation_velocity(p: ArrayLike, v_l: float, w_l: float) -> FloatArray:
    """Eq. 6-9 in rigid-body form: velocity of leader-frame point p, (-w_l y, v_l + w_l x).

    Expressed in the leader frame, (n, 2) m/s. With w_l = 0 it is (0, v_l) as
    the paper states; it is what a follower must do to stay at p.
    """
    q = np.atleast_2d(np.asarray(p, dtype=np.float64))
    return np.stack([-w_l * q[:, 1], v_l + w_l * q[:, 0]], axis=1)


def compensation_velocity_paper(p: ArrayLike, v_l: float, w_l: float) -> FloatArray:
    """Eq. 6-9 exactly as printed (for comparison only; see the module docstring).

    r = v_l / w_l, r_i = sqrt((r + x)^2 + y^2), phi = arctan(y / (r + x)),
    v_i = w_l r_i, (v_ix, v_iy) = v_i (cos(phi + pi/2), sin(phi + pi/2)).
    Valid only for w_l > 0 and r + x > 0; elsewhere it is wrong or undefined.
    """
    q = np.atleast_2d(np.asarray(p, dtype=np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.float64(v_l) / np.float64(w_l)
        r_i = np.sqrt((r + q[:, 0]) ** 2 + q[:, 1] ** 2)
        phi = np.arctan(q[:, 1] / (r + q[:, 0]))
    v_i = w_l * r_i
    return np.stack([v_i * np.cos(phi + np.pi / 2), v_i * np.sin(phi + np.pi / 2)], axis=1)


def lyapunov(p: ArrayLike, p_d: ArrayLike) -> FloatArray:
    """Eq. 21 per follower: V_i = 1/2 ||rho_d,i - rho_i||^2, (n,) m^2. The team's V is the sum."""
    err = np.asarray(p_d, dtype=np.float64) - np.asarray(p, dtype=np.float64)
    return 0.5 * np.sum(err * err, axis=-1)


@kernel
def controller_kernel(
    p: FloatArray,
    a: FloatArray,
    p_d: FloatArray,
    p_d_dot: FloatArray,
    v_l: float,
    w_l: float,
    g: FloatArray,
    dt: float,
    active: BoolArray,
    state: FloatArray,
    out: FloatArray,
) -> None:
    """Eq. 3-12 for every follower, in place.

    ``g``: gains in GAIN_INDEX order. ``state`` (n, 5) is read and updated:
    [a_r, a_r_dot, valid, v_prev, w_prev]. ``out`` (n, 8) receives
    [v, w, zeta_rx, zeta_ry, a_r, a_err, a_r_dot, V].
    """
    n = p.shape[0]
    for i in range(n):
        ex = p_d[i, 0] - p[i, 0]
        ey = p_d[i, 1] - p[i, 1]
        # eq. 3-4: pose controller, saturated per component
        fx = p_d_dot[i, 0] + saturate_position_error(ex, g[_K_F1], g[_K_F2], g[_A])
        fy = p_d_dot[i, 1] + saturate_position_error(ey, g[_K_F1], g[_K_F2], g[_A])
        # eq. 5-9: plus the velocity of the leader-frame point the follower is at
        zx = fx - w_l * p[i, 1]
        zy = fy + v_l + w_l * p[i, 0]
        speed = math.hypot(zx, zy)
        valid = state[i, 2] > 0.5
        if speed > REFERENCE_SPEED_EPS:
            a_r = math.atan2(zy, zx)
        elif valid:
            a_r = state[i, 0]
        else:
            a_r = a[i]
        # a_r_dot: wrapped change of a_r over dt, optionally low-passed
        if valid:
            raw_rate = wrap_angle(a_r - state[i, 0]) / dt
            prev_rate = state[i, 1]
        else:
            raw_rate = 0.0
            prev_rate = 0.0
        if g[_TAU_AR] > 0.0:
            a_r_dot = prev_rate + dt / (g[_TAU_AR] + dt) * (raw_rate - prev_rate)
        else:
            a_r_dot = raw_rate
        a_err = wrap_angle(a_r - a[i])
        v_c = speed * math.cos(a_err)  # eq. 10
        w_c = a_r_dot + heading_saturation(a_err, g[_K_W1], g[_K_W2]) + w_l  # eq. 11-12
        if active[i]:
            v_c = clamp_command(v_c, state[i, 3], g[_V_MAX], g[_ACC_V] * dt)
            w_c = clamp_command(w_c, state[i, 4], g[_W_MAX], g[_ACC_W] * dt)
            state[i, 0] = a_r
            state[i, 1] = a_r_dot
            state[i, 2] = 1.0
        else:
            # A follower that may not move stops at once (no ramp) and forgets a_r.
            v_c = 0.0
            w_c = 0.0
            state[i, 0] = a_r
            state[i, 1] = 0.0
            state[i, 2] = 0.0
        state[i, 3] = v_c
        state[i, 4] = w_c
        out[i, 0] = v_c
        out[i, 1] = w_c
        out[i, 2] = zx
        out[i, 3] = zy
        out[i, 4] = a_r
        out[i, 5] = a_err
        out[i, 6] = a_r_dot
        out[i, 7] = 0.5 * (ex * ex + ey * ey)  # eq. 21


@dataclass(frozen=True)
class ControllerState:
    """What the controller remembers between ticks: (n, 5) [a_r, a_r_dot, valid, v, w]."""

    memory: FloatArray

    @staticmethod
    def initial(n: int) -> "ControllerState":
        return ControllerState(np.zeros((n, 5)))

    @property
    def last_commands(self) -> Commands:
        return Commands(self.memory[:, 3].copy(), self.memory[:, 4].copy())


@dataclass(frozen=True)
class ControlOutput:
    """One tick of the controller: the commands and what led to them (for plots and logs)."""

    commands: Commands
    state: ControllerState
    zeta_r: FloatArray  # (n, 2) reference velocity, eq. 5
    a_r: FloatArray  # (n,) reference angle
    a_err: FloatArray  # (n,) a~ = wrap(a_r - a)
    a_r_dot: FloatArray  # (n,) reference-angle rate used in eq. 11
    v_lyap: FloatArray  # (n,) eq. 21

    @staticmethod
    def idle(commands: FloatArray) -> "ControlOutput":
        """Commands that did not come from the controller (start-up manoeuvres, STOP): (n, 2)."""
        c = np.asarray(commands, dtype=np.float64).reshape(-1, 2)
        n = c.shape[0]
        z2, z1 = np.zeros((n, 2)), np.zeros(n)
        return ControlOutput(Commands(c[:, 0].copy(), c[:, 1].copy()), ControllerState.initial(n),
                             z2, z1.copy(), z1.copy(), z1.copy(), z1.copy())


def compute_commands(
    p: ArrayLike,
    a: ArrayLike,
    p_d: ArrayLike,
    p_d_dot: ArrayLike,
    v_l: float,
    w_l: float,
    gains: Gains,
    state: ControllerState,
    dt: float,
    active: ArrayLike | None = None,
) -> ControlOutput:
    """Eq. 3-12 for all followers: leader-frame poses -> (v, w) commands, always within limits.

    ``active`` (n,) marks followers that may move; an inactive follower (lost,
    stopped) gets (0, 0) at once, bypassing the acceleration limit.
    """
    if not dt > 0.0:
        raise ValueError(f"dt = {dt!r}: must be > 0 s")
    p_arr = np.ascontiguousarray(np.atleast_2d(np.asarray(p, dtype=np.float64)))
    n = p_arr.shape[0]
    a_arr = np.ascontiguousarray(np.asarray(a, dtype=np.float64).reshape(n))
    pd_arr = float_rows(p_d, (n, 2))
    pdd_arr = float_rows(p_d_dot, (n, 2))
    act = np.ones(n, dtype=np.bool_) if active is None else np.asarray(active, dtype=np.bool_).reshape(n)
    memory = state.memory.copy()
    out = np.empty((n, 8))
    controller_kernel(p_arr, a_arr, pd_arr, pdd_arr, float(v_l), float(w_l), gains.as_array(), float(dt), act, memory, out)
    return ControlOutput(
        commands=Commands(out[:, 0].copy(), out[:, 1].copy()),
        state=ControllerState(memory),
        zeta_r=out[:, 2:4].copy(),
        a_r=out[:, 4].copy(),
        a_err=out[:, 5].copy(),
        a_r_dot=out[:, 6].copy(),
        v_lyap=out[:, 7].copy(),
    )
