"""The tuning bench's pure parts: which saturation or limit is active, V's trend, the score of
a step, gain ranges, and a step test in the simulator."""

from __future__ import annotations

import math
import re
import warnings

import numpy as np
import pytest

from core.control.formation import ControllerState, compute_commands
from core.control.tuning import (EQ4, EQ12, FILTER, V_LIMIT, W_LIMIT, StepTest, check_step_test, flag_names,
                                 limit_flags, lyapunov_rate, lyapunov_trend, parse_gain_range, score_step,
                                 stepped_slots, sweep_grid)
from core.sim.sweep import run_step_test, settled_start, step_scenario
from core.types import Gains

from tests.helpers import SCENARIOS


def _flags(p, p_d, a, gains=Gains(), prev=None, v_l=0.0, w_l=0.0, active=None, filt=None):
    n = len(p)
    state = ControllerState.initial(n)
    if prev is not None:
        state.memory[:, 3:5] = prev
    out = compute_commands(p, a, p_d, np.zeros((n, 2)), v_l, w_l, gains, state, 1 / 30, active)
    return limit_flags(p, p_d, out.a_err, out.zeta_r, out.a_r_dot, w_l,
                       np.column_stack([out.commands.v, out.commands.w]), gains, active, filt)


def test_each_saturation_and_limit_is_named_where_it_acts():
    g = Gains()
    # a small error straight ahead, already moving at the speed asked: nothing saturates
    calm = _flags([[0.0, 0.0]], [[0.0, 0.005]], [math.pi / 2], prev=np.array([[0.005, 0.0]]))
    assert calm[0] == 0, flag_names(int(calm[0]))
    # 1 m of error is far beyond a = 0.1 m: eq. 4 gives much less than k_f1/a * e
    far = _flags([[0.0, 0.0]], [[0.0, 1.0]], [math.pi / 2])
    assert far[0] & EQ4
    # facing away from the target: eq. 12's tanh^3 is at its bound k_w1
    away = _flags([[0.0, 0.0]], [[0.0, 0.02]], [-math.pi / 2])
    assert away[0] & EQ12
    # from rest, a command that wants more than one tick's acceleration is clamped
    assert far[0] & V_LIMIT
    spin = _flags([[0.0, 0.0]], [[0.02, 0.0]], [math.pi / 2], gains=g.replace(accel_w_max=0.1))
    assert spin[0] & W_LIMIT
    # a follower that may not move has nothing active; the filter's flag comes from the filter
    assert _flags([[0.0, 0.0]], [[0.0, 1.0]], [math.pi / 2], active=[False])[0] == 0
    assert _flags([[0.0, 0.0]], [[0.0, 0.005]], [math.pi / 2], prev=np.array([[0.005, 0.0]]), filt=[True])[0] == FILTER
    assert flag_names(EQ4 | W_LIMIT) == ["eq. 4 saturated", "ω limit"]


def test_the_compiled_flags_and_slopes_follow_the_documented_rules_on_awkward_input():
    """limit_flags and lyapunov_rate are compiled loops: against the rules written out in numpy
    (eq. 4's ratio NaN at e = 0, NaN poses, ±inf errors; V's mean and sum skipping NaNs, a
    follower with no V at all flat) on random teams."""
    from core.control.formation import heading_saturation, saturate_position_error

    rng = np.random.default_rng(7)
    for _ in range(300):
        n = int(rng.integers(1, 7))
        p = rng.normal(scale=float(rng.choice([0.01, 0.1, 1.0])), size=(n, 2))
        p_d = rng.normal(scale=0.3, size=(n, 2))
        j = int(rng.integers(2))
        p_d[0, j] = p[0, j] if rng.random() < 0.5 else p_d[0, j]  # no error in one component: eq. 4's ratio is NaN
        p_d[0] = p[0] if rng.random() < 0.2 else p_d[0]
        if rng.random() < 0.3:
            p[int(rng.integers(n)), int(rng.integers(2))] = rng.choice([np.nan, np.inf, -np.inf])
        a_err, zeta, a_r_dot, w_l = rng.uniform(-4, 4, n), rng.normal(scale=0.2, size=(n, 2)), rng.normal(size=n), 0.3
        g = Gains(k_f1=float(rng.uniform(0.05, 1.0)), a=float(rng.uniform(0.02, 1.0)))
        v_raw = np.hypot(zeta[:, 0], zeta[:, 1]) * np.cos(a_err)
        cmd = rng.normal(size=(n, 2))
        keep = rng.random(n) < 0.5
        cmd[keep, 0] = v_raw[keep]
        active, filt = rng.random(n) < 0.8, rng.random(n) < 0.3
        err = p_d - p
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = saturate_position_error(err, g.k_f1, g.k_f2, g.a) / (g.k_f1 / g.a * err)
        heading = heading_saturation(a_err, g.k_w1, g.k_w2)
        want = (np.where(np.any(ratio < 0.5, axis=1), EQ4, 0) | np.where(np.abs(heading) > 0.5 * g.k_w1, EQ12, 0)
                | np.where(np.abs(cmd[:, 0] - v_raw) > 1e-9, V_LIMIT, 0)
                | np.where(np.abs(cmd[:, 1] - (a_r_dot + heading + w_l)) > 1e-9, W_LIMIT, 0) | np.where(filt, FILTER, 0))
        got = limit_flags(p, p_d, a_err, zeta, a_r_dot, w_l, cmd, g, active, filt)
        assert got.tolist() == np.where(active, want, 0).tolist()

        k = int(rng.integers(2, 40))
        t, v = np.sort(rng.uniform(0.0, 0.5, k)), rng.normal(scale=1e-3, size=(k, n))
        v[rng.random((k, n)) < 0.3] = np.nan
        v[:, 0] = np.nan if rng.random() < 0.3 else v[:, 0]
        tc = t - t.mean()
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # nanmean of a column with no V
            ref = np.nansum(tc[:, None] * (v - np.nanmean(v, axis=0)), axis=0) / np.sum(tc * tc)
        np.testing.assert_allclose(lyapunov_rate(t, v), ref, rtol=1e-9, atol=1e-15)
    assert lyapunov_rate([0.0, 0.1, 0.2], [[np.nan], [np.nan], [np.nan]]).tolist() == [0.0]


def test_lyapunov_rate_is_the_slope_and_the_trend_has_a_dead_band():
    t = np.linspace(0.0, 0.5, 16)
    v = np.column_stack([1e-3 - 2e-3 * t, 5e-4 + 1e-6 * t, 1e-4 + 4e-4 * t])
    rate = lyapunov_rate(t, v)
    np.testing.assert_allclose(rate, [-2e-3, 1e-6, 4e-4], atol=1e-12)
    assert lyapunov_trend(rate).tolist() == [-1, 0, 1]
    # under a 1 cm error V follows the measurement noise: flat whatever its slope
    assert lyapunov_trend(rate, [1e-3, 5e-4, 1e-5]).tolist() == [-1, 0, 0]
    assert lyapunov_rate([0.0], [[1.0]]).tolist() == [0.0]


def _first_order(t, t0, size, tau, overshoot=0.0):
    """A follower moving from 0 to ``size`` (x) after t0: first order, plus an optional bump past it."""
    s = np.clip(t - t0, 0.0, None)
    x = size * (1 - np.exp(-s / tau)) + overshoot * np.sin(np.clip(s, 0, math.pi)) * (s < math.pi)
    return np.column_stack([x, np.zeros_like(t)])


def test_score_step_measures_settling_overshoot_rms_and_effort():
    dt = 1 / 30
    t = np.arange(0.0, 12.0, dt)
    t0, size, tau = 2.0, 0.10, 0.5
    p = _first_order(t, t0, size, tau)[:, None, :]
    target = np.broadcast_to(np.array([[size, 0.0]]), p.shape)
    cmd = np.zeros((len(t), 1, 2))
    cmd[:, 0, 0] = 0.1  # 0.1 m/s for the whole window: effort 0.01 m²/s² x 8 s
    score = score_step(t, p, target, cmd, t0, 8.0, wheel_base_m=0.12)
    expected = tau * math.log(size / 0.02)  # the error falls under 2 cm here
    assert abs(score.settling_s[0] - expected) <= dt + 1e-9
    assert score.overshoot_m[0] == 0.0
    assert score.steady_rms_m[0] < 1e-4
    assert score.effort[0] == pytest.approx(0.01 * 8.0, rel=0.01)
    # a bump past the target is the overshoot
    bumped = _first_order(t, t0, size, tau, overshoot=0.03)[:, None, :]
    s2 = score_step(t, bumped, target, cmd, t0, 8.0, 0.12)
    assert 0.015 < s2.overshoot_m[0] < 0.03
    # not settled within the window: NaN, and the team's settling is NaN too
    slow = _first_order(t, t0, size, 10.0)[:, None, :]
    s3 = score_step(t, slow, target, cmd, t0, 8.0, 0.12)
    assert math.isnan(s3.settling_s[0]) and math.isnan(s3.worst["settling_s"])
    # an untracked (NaN) position is outside the tolerance
    lost = p.copy()
    lost[t > 9.8] = np.nan  # lost over the last ticks of the window
    assert math.isnan(score_step(t, lost, target, cmd, t0, 8.0, 0.12).settling_s[0])


def test_gain_ranges_refuse_what_cannot_be_swept_naming_the_bound():
    r = parse_gain_range("k_w2=1:4:7")
    assert r.name == "k_w2" and r.values.tolist() == pytest.approx([1, 1.5, 2, 2.5, 3, 3.5, 4])
    assert parse_gain_range("k_f1=0.2").values.tolist() == [0.2]
    for text, needle in [
        ("k_w2=4:1:5", "reversed"), ("k_w2=2:2:5", "empty"), ("k_w2=1:4:0", "COUNT"), ("k_w2=1:25:5", "(0, 20]"),
        ("k_f1=0:0.5:3", "(0, 1]"), ("gain=1:2:3", "NAME one of"), ("k_w2=a:b:c", "numbers"), ("k_w2=1:2", "LO:HI:COUNT"),
        ("k_w2=1:4:2.5", "COUNT"), ("k_w2=nan:4:3", "(0, 20]"),
    ]:
        with pytest.raises(ValueError, match=re.escape(needle)):
            parse_gain_range(text)
    grid = sweep_grid([parse_gain_range("k_w2=1:4:5"), parse_gain_range("k_f1=0.05:0.3:5")], Gains())
    assert len(grid) == 25 and grid[0].k_w2 == 1.0 and grid[0].k_f1 == 0.05 and grid[1].k_f1 > 0.05
    assert grid[5].k_w2 > 1.0 and grid[0].a == Gains().a  # the first gain varies slowest; others kept
    with pytest.raises(ValueError, match="must differ"):
        sweep_grid([parse_gain_range("k_w2=1:4:5"), parse_gain_range("k_w2=1:2:3")], Gains())


def test_step_tests_refuse_what_cannot_run():
    assert check_step_test(StepTest("offset", 0, 0.1), 3) is None
    assert "followers 1..3" in (check_step_test(StepTest("offset", 5, 0.1), 3) or "")
    assert "cm" in (check_step_test(StepTest("offset", 0, 2.0), 3) or "")
    assert "deg/s" in (check_step_test(StepTest("turn", 0, math.radians(90)), 3) or "")
    assert "one of" in (check_step_test(StepTest("switch", formation="blob"), 3) or "")
    assert "window" in (check_step_test(StepTest(window_s=0.5), 3) or "")
    s = stepped_slots(StepTest("offset", 1, 0.1), np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([1, 0]))
    assert s.tolist() == [[0.1, 0.0], [1.0, 0.0]]  # follower 2 holds slot 1


def _experiment1():
    from core.config import parse_scenario

    return parse_scenario((SCENARIOS / "experiment1.toml").read_text(), "experiment1.toml")


def test_a_step_in_the_simulator_settles_and_scores_like_the_gains_say():
    base = settled_start(_experiment1())
    test = StepTest("offset", 0, 0.10, window_s=10.0)
    sc = step_scenario(base, test, (0.06, 0.0))
    assert sc.switches and sc.switches[0][0] == pytest.approx(3.0) and sc.duration_s == pytest.approx(13.0)
    good = run_step_test(base, test, (0.06, 0.0), base.gains)
    assert 0.5 < good.score.settling_s[0] < 5.0, good.score
    assert good.score.steady_rms_m[0] < 0.01
    # a tiny k_f1 (position gain k_f1/a = 0.5 /s) does not settle a 10 cm step in 10 s
    weak = run_step_test(base, test, (0.06, 0.0), base.gains.replace(k_f1=0.01, k_f2=0.0))
    assert math.isnan(weak.score.settling_s[0])
    # a turn step moves every follower off its slot in the world; they come back
    turn = run_step_test(base, StepTest("turn", 0, math.radians(10.0)), (0.06, 0.0), base.gains)
    assert np.all(np.isfinite(turn.score.settling_s)) and turn.score.overshoot_m.max() > 0.0





def test_the_best_sweep_point_settles_fast_without_giving_up_steady_error():
    """A point that settles fastest but holds three times the steady error of another is not
    "best" (core.sim.sweep.BEST_RULE): among settled points with a steady error near the
    smallest, the fastest; an unsettled point never beats a settled one."""
    import numpy as np

    from core.control.tuning import GainRange, StepScore, StepTest
    from core.sim.sweep import BEST_RULE, SweepResult
    from core.types import Gains

    def score(settle: float, rms_cm: float, over_cm: float = 1.0) -> StepScore:
        return StepScore(np.array([settle]), np.array([over_cm / 100]), np.array([rms_cm / 100]), np.array([0.1]), 300)

    scores = (score(1.7, 0.79), score(2.4, 0.19), score(2.2, 0.26), score(float("nan"), 0.05), None)
    result = SweepResult((GainRange("k_f1", np.linspace(0.05, 0.25, 5)),), StepTest("offset", 0, 0.1, "", 10.0),
                         "truth", tuple(Gains(k_f1=v) for v in np.linspace(0.05, 0.25, 5)), scores, 1.0)
    assert result.best() == 2  # 0.26 cm is within 1.5 x 0.19 + 0.05; it settles sooner than the 0.19 one
    assert result.order() == [2, 1, 0, 3, 4]  # then the slow precise one, the fast sloppy one, the unsettled, not run
    assert "steady error" in BEST_RULE


def test_the_limits_named_after_the_send_are_the_steps_own():
    """The live loop takes its step with limits=False and names the limits once the commands are
    sent (core.control.step.step_limits): the very flags team_step gives with limits=True, the
    filter's bits included, over many ticks where each limit and the filter act."""
    from core.control.safety import SafetySettings
    from core.control.step import TeamMemory, step_limits, team_step

    rng = np.random.default_rng(4)
    gains = Gains(v_max=0.15, w_max=0.8)
    formation = np.array([[-0.6, -0.5], [0.6, -0.5], [0.0, -1.1]])
    p = np.array([[-0.3, -0.5], [1.5, 0.2], [-0.12, -0.5]])  # one far (saturates), two close together
    a = np.array([0.0, -2.0, math.pi])
    memory = TeamMemory.start(p, formation)
    seen = np.zeros(5, dtype=np.int64)
    for k in range(60):
        tracked = np.array([True, True, k % 7 != 0])
        twist = (0.1, 0.3 * math.sin(k / 9))
        obstacles = np.array([[-0.5, -0.5]]) if k % 2 else None  # in the way to a slot
        kw = dict(obstacles=obstacles, safety=SafetySettings(), acting=(p + 0.01, a) if k % 3 == 0 else None)
        full = team_step(memory, p, a, tracked, formation, twist, gains, 1 / 30, **kw)
        later = team_step(memory, p, a, tracked, formation, twist, gains, 1 / 30, limits=False, **kw)
        assert np.array_equal(step_limits(later, gains), full.flags)
        assert np.array_equal(later.control.commands.v, full.control.commands.v)
        for bit, flag in enumerate((EQ4, EQ12, V_LIMIT, W_LIMIT, FILTER)):
            seen[bit] += int(np.any(full.flags & flag))
        memory = full.memory
        p = p + 0.02 * rng.standard_normal(p.shape)
        a = a + 0.05 * rng.standard_normal(a.shape)
    assert (seen > 0).all(), seen  # every limit and the filter acted in some tick
