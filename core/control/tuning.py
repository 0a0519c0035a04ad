"""Measuring what gains do: which saturation or limit each follower is in, the trend of
eq. 21's Lyapunov function per follower, and the score of a step test.

Paper §2 proves V = ½‖ρ̃‖² (eq. 21) non-increasing outside saturation. What slows a follower
down is one of:

* **eq. 4 saturated**: the pose term f(e) = (k_f1 + k_f2 tanh|e|)/(a + |e|)·e of one error
  component gives less than half of what its small-error gain k_f1/a would (|e| ≳ a): the
  error shrinks at a bounded speed instead of exponentially;
* **eq. 12 saturated**: the heading term k_w1 tanh³(k_w2 ã) is past half its bound k_w1: the
  heading turns at a bounded rate;
* **v limit / ω limit**: the command was clamped (v_max, ω_max or the acceleration limits,
  core.control.limits);
* **safety filter**: one of the barrier constraints is at its limit (core.control.safety).

:func:`limit_flags` returns these as bits per follower; :func:`lyapunov_rate` and
:func:`lyapunov_trend` say whether V is falling, flat or rising.

A step test (:class:`StepTest`) moves one follower's slot, switches the formation, or steps
the leader's turn rate; :func:`score_step` measures each follower's response on what the
controller saw (estimated positions against the targets of the formation as set): settling
time to 2 cm, overshoot, steady error RMS and control effort. The live page, the simulator
sweeps and ``report`` all score with this one function.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from core.control.formation import heading_saturation, saturate_position_error
from core.control.presets import FORMATION_PRESETS, formation_preset
from core.jit import kernel
from core.types import GAIN_BOUNDS, BoolArray, FloatArray, Gains, IntArray

LIMIT_NAMES = ("eq. 4 saturated", "eq. 12 saturated", "v limit", "ω limit", "safety filter")
EQ4, EQ12, V_LIMIT, W_LIMIT, FILTER = (1 << k for k in range(len(LIMIT_NAMES)))
SATURATED_RATIO = 0.5  # eq. 4: effective gain under half the small-error gain; eq. 12: over half of k_w1
CLAMP_EPS = 1e-9

RATE_WINDOW_S = 0.5  # V's rate: least-squares slope over this much of the past
RATE_FLAT = 1e-5  # m²/s: |dV/dt| under this is flat (1 cm of error changing by 1 mm/s)
V_NOISE = 0.5 * 0.01**2  # m²: V of a 1 cm error; below it V moves with the measurement noise: flat
TRENDS = {-1: "falling", 0: "flat", 1: "rising"}

SETTLE_TOL_M = 0.02
STEADY_S = 2.0  # the steady error is the RMS over the last this-many seconds of the window
STEP_KINDS = ("offset", "switch", "turn")
WINDOW_S = (3.0, 60.0)  # allowed measuring windows (s)
OFFSET_M = (0.01, 0.5)  # allowed offset sizes (m, either sign)
TURN_RPS = (math.radians(1.0), math.radians(30.0))  # allowed turn steps (either sign)


@kernel
def _limit_flags_kernel(err: FloatArray, a_err: FloatArray, zeta_r: FloatArray, a_r_dot: FloatArray, w_l: float,
                        commands: FloatArray, k_f1: float, k_f2: float, a: float, k_w1: float, k_w2: float,
                        active: BoolArray, filter_active: BoolArray, out: IntArray) -> None:
    small_gain = k_f1 / a
    for i in range(err.shape[0]):
        flags = 0
        for j in range(2):
            e = err[i, j]
            den = small_gain * e
            f = saturate_position_error(e, k_f1, k_f2, a)
            if den != 0.0:
                ratio = f / den
            elif f == 0.0 or math.isnan(f):  # 0/0, NaN: not saturated
                ratio = math.nan
            else:  # as IEEE division by a signed zero gives it
                ratio = math.copysign(math.inf, f) * math.copysign(1.0, den)
            if ratio < SATURATED_RATIO:
                flags |= EQ4
        heading = heading_saturation(a_err[i], k_w1, k_w2)  # eq. 12, as the controller computed it
        if abs(heading) > SATURATED_RATIO * k_w1:
            flags |= EQ12
        v_raw = math.hypot(zeta_r[i, 0], zeta_r[i, 1]) * math.cos(a_err[i])
        w_raw = a_r_dot[i] + heading + w_l
        if abs(commands[i, 0] - v_raw) > CLAMP_EPS:
            flags |= V_LIMIT
        if abs(commands[i, 1] - w_raw) > CLAMP_EPS:
            flags |= W_LIMIT
        if filter_active[i]:
            flags |= FILTER
        out[i] = flags if active[i] else 0


def limit_flags(
    p: ArrayLike,
    p_d: ArrayLike,
    a_err: ArrayLike,
    zeta_r: ArrayLike,
    a_r_dot: ArrayLike,
    w_l: float,
    commands: ArrayLike,
    gains: Gains,
    active: ArrayLike | None = None,
    filter_active: ArrayLike | None = None,
) -> IntArray:
    """(n,) bit flags (EQ4 | EQ12 | V_LIMIT | W_LIMIT | FILTER) for one tick of the controller.

    ``commands`` (n, 2) are the controller's (before the safety filter); the unclamped
    command is rebuilt from eq. 10-11 (v = |ζ_r| cos ã, ω = ȧ_r + f(ã) + ω_l). A follower
    that may not move (``active`` false) has no flags. Eq. 4 is saturated where its term is
    under SATURATED_RATIO of the small-error gain's (NaN, at e = 0: not saturated). One
    compiled pass: the live loop asks this every tick, for the page."""
    f64, c = np.float64, np.ascontiguousarray  # one layout, hence one compiled signature (app.live.warmup)
    ae = c(np.asarray(a_err, dtype=f64).reshape(-1))
    n = ae.shape[0]
    err = c((np.asarray(p_d, dtype=f64) - np.asarray(p, dtype=f64)).reshape(n, 2))
    act = np.ones(n, dtype=np.bool_) if active is None else c(np.asarray(active, dtype=np.bool_).reshape(n))
    filt = np.zeros(n, dtype=np.bool_) if filter_active is None else c(np.asarray(filter_active, dtype=np.bool_).reshape(n))
    out = np.empty(n, dtype=np.int64)
    g = gains
    _limit_flags_kernel(err, ae, c(np.asarray(zeta_r, dtype=f64).reshape(n, 2)), c(np.asarray(a_r_dot, dtype=f64).reshape(n)),
                        float(w_l), c(np.asarray(commands, dtype=f64).reshape(n, 2)), float(g.k_f1), float(g.k_f2),
                        float(g.a), float(g.k_w1), float(g.k_w2), act, filt, out)
    return out


def flag_names(flags: int) -> list[str]:
    """The names of the bits set in one follower's flags."""
    return [name for k, name in enumerate(LIMIT_NAMES) if int(flags) & (1 << k)]


@kernel
def _slopes_kernel(tc: FloatArray, v: FloatArray, den: float, out: FloatArray) -> None:
    # per column: NaN-skipping mean, then the NaN-skipping sum of tc * (v - mean), each summed row
    # by row (the order numpy's nanmean and nansum along axis 0 add in)
    for j in range(v.shape[1]):
        total = 0.0
        count = 0
        for k in range(v.shape[0]):
            if not math.isnan(v[k, j]):
                total += v[k, j]
                count += 1
        mean = total / count if count else math.nan
        acc = 0.0
        for k in range(v.shape[0]):
            term = tc[k] * (v[k, j] - mean)
            if not math.isnan(term):
                acc += term
        out[j] = acc / den


def lyapunov_rate(t: ArrayLike, v: ArrayLike) -> FloatArray:
    """dV/dt per follower (m²/s): the least-squares slope of V (K, n) over times t (K,), NaNs
    skipped (a follower with no V at all: 0)."""
    tt = np.asarray(t, dtype=np.float64)
    vv = np.asarray(v, dtype=np.float64)
    if tt.size < 2 or vv.ndim != 2:
        return np.zeros(vv.shape[-1] if vv.ndim else 0)
    tc = tt - tt.mean()
    den = float(np.sum(tc * tc))
    if den <= 0.0:
        return np.zeros(vv.shape[1])
    out = np.empty(vv.shape[1])
    _slopes_kernel(np.ascontiguousarray(tc), np.ascontiguousarray(vv), den, out)
    return out


def lyapunov_trend(rate: ArrayLike, v: ArrayLike | None = None, flat: float = RATE_FLAT) -> IntArray:
    """-1 falling, 0 flat, +1 rising, per follower; flat too while V (if given) is under
    V_NOISE, where it only follows the measurement noise."""
    r = np.nan_to_num(np.asarray(rate, dtype=np.float64))
    trend = np.where(r < -flat, -1, np.where(r > flat, 1, 0))
    if v is not None:
        trend = np.where(np.nan_to_num(np.asarray(v, dtype=np.float64)) < V_NOISE, 0, trend)
    return trend.astype(np.int64)


@dataclass(frozen=True)
class StepTest:
    """One step test: what is stepped, and how long the response is measured.

    ``offset``: follower ``follower``'s slot moves ``size`` m sideways (+x, the leader's right);
    ``switch``: the formation switches to the preset ``formation``;
    ``turn``: the leader's turn rate steps by ``size`` rad/s (counter-clockwise positive)."""

    kind: str = "offset"
    follower: int = 0  # 0-based
    size: float = 0.10
    formation: str = "line abreast"
    window_s: float = 10.0

    def label(self) -> str:
        if self.kind == "offset":
            return f"offset F{self.follower + 1} {self.size * 100:+.0f} cm"
        if self.kind == "switch":
            return f"switch to {self.formation}"
        return f"turn step {math.degrees(self.size):+.1f} deg/s"


def check_step_test(test: StepTest, n: int) -> str | None:
    """Why this test cannot be run on a team of n followers (one line), or None."""
    if test.kind not in STEP_KINDS:
        return f"test {test.kind!r}: must be one of {', '.join(STEP_KINDS)}"
    if not (math.isfinite(test.window_s) and WINDOW_S[0] <= test.window_s <= WINDOW_S[1]):
        return f"window {test.window_s!r} s: must be in [{WINDOW_S[0]:g}, {WINDOW_S[1]:g}] s"
    if test.kind == "offset":
        if not 0 <= test.follower < n:
            return f"follower {test.follower + 1}: the team has followers 1..{n}"
        if not (math.isfinite(test.size) and OFFSET_M[0] <= abs(test.size) <= OFFSET_M[1]):
            return (f"offset {test.size * 100 if math.isfinite(test.size) else test.size!r} cm: must be"
                    f" {OFFSET_M[0] * 100:g} to {OFFSET_M[1] * 100:g} cm either way")
    elif test.kind == "switch":
        if test.formation not in FORMATION_PRESETS:
            return f"formation {test.formation!r}: must be one of {', '.join(FORMATION_PRESETS)}"
    elif not (math.isfinite(test.size) and TURN_RPS[0] - 1e-12 <= abs(test.size) <= TURN_RPS[1] + 1e-12):
        return (f"turn step {math.degrees(test.size) if math.isfinite(test.size) else test.size!r} deg/s: must be"
                f" {math.degrees(TURN_RPS[0]):g} to {math.degrees(TURN_RPS[1]):g} deg/s either way")
    return None


def stepped_slots(test: StepTest, slots: ArrayLike, assignment: ArrayLike) -> FloatArray:
    """The formation (m, 2) after an offset or switch step; a turn step leaves it as it is."""
    s = np.array(slots, dtype=np.float64)
    n = np.asarray(assignment).shape[0]
    if test.kind == "offset":
        s[int(np.asarray(assignment)[test.follower])] += (test.size, 0.0)
        return s
    if test.kind == "switch":
        return formation_preset(test.formation, n)
    return s


@dataclass(frozen=True)
class StepScore:
    """Each follower's response to a step, measured over the test's window."""

    settling_s: FloatArray  # (n,) from the step until the error stays within 2 cm; NaN: not within the window
    overshoot_m: FloatArray  # (n,) past the target along the step's direction (a follower not stepped: peak error)
    steady_rms_m: FloatArray  # (n,) error RMS over the window's last STEADY_S
    effort: FloatArray  # (n,) ∫ mean squared wheel speed dt, m²/s
    ticks: int  # rows measured

    @property
    def worst(self) -> dict[str, float]:
        """The team's figures: the slowest settling (NaN if any did not settle), the largest
        overshoot, the steady RMS over all followers, the summed effort."""
        return {"settling_s": float(np.max(self.settling_s)) if self.settling_s.size else math.nan,
                "overshoot_m": float(np.nanmax(self.overshoot_m)) if self.overshoot_m.size else math.nan,
                "steady_rms_m": float(np.sqrt(np.nanmean(self.steady_rms_m ** 2))) if self.steady_rms_m.size else math.nan,
                "effort": float(np.nansum(self.effort))}


def score_step(
    t: ArrayLike,
    p: ArrayLike,
    target: ArrayLike,
    commands: ArrayLike,
    t0: float,
    window_s: float,
    wheel_base_m: float,
    tol_m: float = SETTLE_TOL_M,
    steady_s: float = STEADY_S,
) -> StepScore:
    """Score a step applied at ``t0`` over ``[t0, t0 + window_s]``.

    ``t`` (T,) s, ``p`` (T, n, 2) positions the controller saw, ``target`` (T, n, 2) the
    formation's targets (after the step), ``commands`` (T, n, 2) v, ω. An untracked position
    (NaN) counts as outside the tolerance."""
    tt = np.asarray(t, dtype=np.float64)
    pp = np.asarray(p, dtype=np.float64)
    tg = np.asarray(target, dtype=np.float64)
    cc = np.asarray(commands, dtype=np.float64)
    rows = np.flatnonzero((tt >= t0 - 1e-9) & (tt <= t0 + window_s + 1e-9))
    n = pp.shape[1]
    if rows.size < 2:
        nan = np.full(n, math.nan)
        return StepScore(nan, nan.copy(), nan.copy(), nan.copy(), int(rows.size))
    tw, pw, gw, cw = tt[rows], pp[rows], tg[rows], cc[rows]
    diff = pw - gw  # (K, n, 2) past the target is positive along the step's direction
    err = np.linalg.norm(diff, axis=-1)
    outside = ~(err <= tol_m)  # NaN is outside
    settling = np.full(n, math.nan)
    overshoot = np.zeros(n)
    for i in range(n):
        above = np.flatnonzero(outside[:, i])
        if above.size == 0:
            settling[i] = 0.0
        elif above[-1] < len(tw) - 1:
            settling[i] = float(tw[above[-1] + 1] - t0)
        step = gw[0, i] - pw[0, i]
        size = float(np.hypot(*step)) if np.all(np.isfinite(step)) else 0.0
        if size >= tol_m:
            overshoot[i] = max(0.0, float(np.nanmax(diff[:, i] @ (step / size))))
        else:
            overshoot[i] = float(np.nanmax(err[:, i])) if np.isfinite(err[:, i]).any() else math.nan
    steady = tw >= tw[-1] - steady_s
    with np.errstate(invalid="ignore"):
        steady_rms = np.sqrt(np.nanmean(err[steady] ** 2, axis=0))
    half = wheel_base_m / 2
    power = cw[:, :, 0] ** 2 + (half * cw[:, :, 1]) ** 2  # mean of the two wheels' squared speeds
    effort = np.sum(0.5 * (power[1:] + power[:-1]) * np.diff(tw)[:, None], axis=0)
    return StepScore(settling, overshoot, steady_rms, effort, int(rows.size))


@dataclass(frozen=True)
class GainRange:
    """One axis of a sweep: a gain and the values it takes."""

    name: str
    values: FloatArray

    def label(self) -> str:
        return f"{self.name}={self.values[0]:g}:{self.values[-1]:g}:{len(self.values)}"


MAX_POINTS_PER_GAIN = 25
MAX_GRID = 225


def parse_gain_range(text: str) -> GainRange:
    """``NAME=LO:HI:COUNT`` (COUNT values from LO to HI, both included) or ``NAME=VALUE``.

    Refused with one line naming what is wrong: an unknown gain, a range that is empty or
    reversed, a value outside the gain's bounds (named), too many points."""
    name, sep, spec = str(text).partition("=")
    name = name.strip()
    if not sep or name not in GAIN_BOUNDS:
        raise ValueError(f"gain range {text!r}: must be NAME=LO:HI:COUNT with NAME one of {', '.join(GAIN_BOUNDS)}")
    parts = spec.split(":")
    try:
        numbers = [float(x) for x in parts]
    except ValueError:
        raise ValueError(f"gain range {text!r}: LO, HI and COUNT must be numbers (e.g. {name}=1:4:7)") from None
    if len(numbers) == 1:
        lo = hi = numbers[0]
        count = 1.0
    elif len(numbers) == 3:
        lo, hi, count = numbers
    else:
        raise ValueError(f"gain range {text!r}: must be {name}=LO:HI:COUNT or {name}=VALUE")
    if not count == int(count) or not 1 <= count <= MAX_POINTS_PER_GAIN:
        raise ValueError(f"gain range {text!r}: COUNT must be a whole number 1..{MAX_POINTS_PER_GAIN}")
    if count == 0 or (count > 1 and lo == hi):
        raise ValueError(f"gain range {text!r}: empty (LO = HI with {int(count)} points)")
    if lo > hi:
        raise ValueError(f"gain range {text!r}: reversed (LO {lo:g} > HI {hi:g}); write {name}={hi:g}:{lo:g}:{int(count)}")
    bound = GAIN_BOUNDS[name]
    for value in (lo, hi):
        try:
            bound.check(name, value)
        except ValueError as exc:
            raise ValueError(f"gain range {text!r}: {exc}") from None
    return GainRange(name, np.linspace(lo, hi, int(count)))


def sweep_grid(ranges: list[GainRange], base: Gains) -> list[Gains]:
    """Every combination of the ranges' values (the first range varies slowest), on ``base``."""
    if not 1 <= len(ranges) <= 2:
        raise ValueError(f"a sweep takes one or two gains, got {len(ranges)}")
    if len(ranges) == 2 and ranges[0].name == ranges[1].name:
        raise ValueError(f"a sweep's two gains must differ (both are {ranges[0].name})")
    total = int(np.prod([len(r.values) for r in ranges]))
    if total > MAX_GRID:
        raise ValueError(f"a sweep of {total} points: at most {MAX_GRID}")
    grids = np.meshgrid(*[r.values for r in ranges], indexing="ij")
    out = []
    for k in range(total):
        idx = np.unravel_index(k, grids[0].shape)
        out.append(base.replace(**{r.name: float(g[idx]) for r, g in zip(ranges, grids)}))
    return out
