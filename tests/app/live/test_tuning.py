"""Step tests on the live loop, recorded and reported; sweeps in the worker process; the
`tune` command and its bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import Params, ParamsStore, default_slots
from app.live.sweep import SweepRunner
from app.live.tuning import StepTests, live_base, trials_csv
from app.recording.reader import read_recording
from app.recording.report import write_report
from app.recording.writer import Recorder
from core.config import MeasurementNoise
from core.control.tuning import StepTest, parse_gain_range
from core.sim.team import FollowerDynamics

from tests.helpers import main_cli


def _team(tmp_path, n=3):
    store = ParamsStore(Params(n_followers=n, slots=default_slots(n), leader_mode="straight"))
    dynamics = FollowerDynamics(actuator_tau_s=0.2, speed_max_mps=0.35, turn_max_rps=2.5, accel_max_mps2=0.6,
                                turn_accel_max_rps2=6.0)
    loop = ServiceLoop(store, Backends(seed=5, dynamics=dynamics,
                                       initial_poses=(default_slots(n), np.full(n, math.pi / 2))), rate_hz=30.0)
    tests = StepTests(store, dynamics.wheel_base_m)
    loop.subscribe(tests.on_tick)
    rec = Recorder(tmp_path / "t.mcap", {"scenario": "tuning"}, store.get())
    loop.subscribe(rec.on_tick)
    store.subscribe(rec.on_params)
    tests.listeners.append(rec.on_trial)
    return store, loop, tests, rec


def _tick(loop, seconds):
    for _ in range(int(round(seconds * 30))):
        loop.tick()


def test_a_step_test_runs_on_the_loop_is_recorded_and_report_agrees_within_one_tick(tmp_path):
    store, loop, tests, rec = _team(tmp_path)
    _tick(loop, 4.0)  # the team catches up with the moving leader
    slots_before = store.get().slots.copy()
    assert tests.request(StepTest("offset", 1, 0.12, window_s=8.0)) is None
    assert "running" in (tests.request(StepTest("offset", 0, 0.1)) or "")  # one test at a time
    _tick(loop, 9.0)
    assert len(tests.trials) == 1
    trial = tests.trials[0]
    assert trial.status == "done" and trial.score is not None
    assert 0.3 < trial.score.settling_s[1] < 6.0, trial.score  # the follower stepped settles
    assert trial.score.overshoot_m[1] < 0.05 and trial.score.effort[1] > trial.score.effort[0]
    np.testing.assert_allclose(store.get().slots, slots_before)  # the formation is set back afterwards
    # a second test with other gains: STOP in the middle aborts it and still restores the slots
    store.update("browser:1", k_f1=0.2)
    _tick(loop, 3.0)
    assert tests.request(StepTest("switch", formation="line abreast", window_s=8.0)) is None
    _tick(loop, 2.0)
    store.update("browser:1", stop=True)
    _tick(loop, 0.5)
    assert tests.trials[-1].status == "aborted: STOP"
    np.testing.assert_allclose(store.get().slots, slots_before)
    assert "STOP is engaged" in (tests.request(StepTest("offset", 0, 0.1)) or "")
    store.update("browser:1", stop=False, paused=True)
    _tick(loop, 0.2)
    assert "paused" in (tests.request(StepTest("offset", 0, 0.1)) or "")
    store.update("browser:1", paused=False)
    _tick(loop, 1.0)
    rec.close()

    csv = trials_csv(tests.trials).decode().splitlines()
    assert len(csv) == 3 and csv[0].startswith("trial,test,status,t0_s,k_f1")
    assert csv[1].split(",")[2] == "done" and "aborted: STOP" in csv[2]

    back = read_recording(tmp_path / "t.mcap")
    assert [t["status"] for t in back.trials] == ["done", "aborted: STOP"]
    assert [e["kind"] for e in back.events].count("trial") == 2
    out = tmp_path / "report"
    out.mkdir()
    write_report(back, out)
    import json

    summary = json.loads((out / "summary.json").read_text())
    rows = summary["step_tests"]
    page, here = rows[0]["page"], rows[0]["report"]
    assert abs(page["settling_s"] - here["settling_s"]) <= 1 / 30 + 1e-9
    assert here["overshoot_m"] == pytest.approx(page["overshoot_m"], abs=1e-5)
    assert here["steady_rms_m"] == pytest.approx(page["steady_rms_m"], abs=1e-5)
    assert "## Step tests" in (out / "summary.md").read_text()
    assert (out / "lyapunov.png").stat().st_size > 20_000


def test_the_loop_publishes_v_trend_and_active_limits():
    slots = default_slots(2)
    store = ParamsStore(Params(n_followers=2, slots=slots, leader_mode="stop"))
    # F1 starts 0.8 m behind its slot (the slots are where the team starts: no ramp): eq. 4 saturates
    start = slots + np.array([[0.0, -0.8], [0.0, 0.0]])
    loop = ServiceLoop(store, Backends(seed=5, initial_poses=(start, np.full(2, math.pi / 2))), rate_hz=30.0)
    _tick(loop, 1.5)
    s = loop.last
    assert s is not None and s.limits is not None and s.v_rate is not None
    assert s.limits[0] & 1, s.limits  # eq. 4 for F1
    assert not s.limits[1] & 1
    assert s.v_rate[0] < -1e-4  # V falls while F1 drives in
    for _ in range(int(30 * 25)):
        loop.tick()
    s = loop.last
    assert not s.limits[0] & 1 and abs(s.v_rate[0]) < 1e-4  # arrived: no saturation, V flat


def test_a_sweep_runs_in_a_worker_and_a_cancel_stops_it(tmp_path):
    store, loop, tests, rec = _team(tmp_path)
    _tick(loop, 2.0)
    rec.close()
    base = live_base(loop.last, store.get(), loop.dynamics, MeasurementNoise(0.003, math.radians(1)), 30.0, 5)
    assert not isinstance(base, str)
    scenario, twist = base
    assert scenario.n == 3 and twist[0] == pytest.approx(store.get().leader_speed_mps)
    runner = SweepRunner()
    progress: list[tuple[int, int]] = []
    runner.on_progress.append(lambda d, t: progress.append((d, t)))
    ranges = [parse_gain_range("k_w2=1:4:3"), parse_gain_range("k_f1=0.05:0.2:3")]
    assert runner.start(scenario, StepTest("offset", 0, 0.1, window_s=6.0), twist, ranges, store.get().gains) is None
    assert "running" in (runner.start(scenario, StepTest(), twist, ranges, store.get().gains) or "")
    result = runner.wait(300)
    assert result is not None and not result.cancelled and all(s is not None for s in result.scores)
    assert progress[-1] == (9, 9) and [d for d, _ in progress] == list(range(1, 10))
    best = result.best()
    assert best is not None and math.isfinite(result.scores[best].worst["settling_s"])
    assert best in result.pareto() or result.pareto()
    # a long sweep cancelled after its first point: the points not started never run
    runner.on_progress.append(lambda d, t: runner.cancel() if d == 1 else None)
    long = [parse_gain_range("k_w2=1:4:10"), parse_gain_range("k_f1=0.05:0.2:10")]
    assert runner.start(scenario, StepTest("offset", 0, 0.1, window_s=6.0), twist, long, store.get().gains) is None
    cancelled = runner.wait(300)
    assert cancelled is not None and cancelled.cancelled
    assert sum(s is not None for s in cancelled.scores) < 10
    # bad ranges are refused before anything runs
    assert "at most" in (runner.start(scenario, StepTest(), twist, [parse_gain_range("k_w2=1:4:20"),
                                                                     parse_gain_range("k_f1=0.05:0.2:20")],
                                      store.get().gains) or "")


def test_tune_writes_the_table_and_the_figure(tmp_path):
    out = tmp_path / "sweep"
    r = main_cli("tune", "experiment1", "--gain", "k_w2=1:4:3", "--gain", "k_f1=0.05:0.2:3", "--out", str(out))
    assert r.returncode == 0, r.stderr
    lines = (out / "sweep.csv").read_text().splitlines()
    assert lines[0].startswith("k_w2,k_f1,settling_s") and len(lines) == 10
    assert (out / "sweep.png").stat().st_size > 20_000
    assert "best" in (out / "summary.md").read_text() and "9 runs in" in r.stdout
    # tune is a study of the two gains (on a local Dask cluster): its files are there, and its
    # numbers are the serial sweep's, point by point
    import pyarrow.dataset as ds

    from app.files import load_scenario
    from app.live.sweep import run_sweep
    from core.sim.sweep import settled_start

    assert ds.dataset(str(out / "study" / "results"), format="parquet").count_rows() == 9
    assert (out / "study" / "manifest.json").exists() and (out / "study" / "summary.md").exists()
    sc = load_scenario("experiment1")
    serial = run_sweep(settled_start(sc), StepTest("offset", 0, 0.1, window_s=10.0), (0.06, 0.0),
                       [parse_gain_range("k_w2=1:4:3"), parse_gain_range("k_f1=0.05:0.2:3")], sc.gains)
    assert serial.csv().splitlines()[1:] == lines[1:]


@pytest.mark.parametrize("args, needle", [
    (["--gain", "k_w2=4:1:5"], "reversed"),
    (["--gain", "k_w2=2:2:5"], "empty"),
    (["--gain", "k_w2=1:30:5"], "(0, 20]"),
    (["--gain", "speed=1:2:3"], "NAME one of"),
    (["--gain", "k_w2=1:2:3", "--gain", "k_f1=0.1:0.2:3", "--gain", "a=0.1:0.2:2"], "one or two gains"),
    (["--gain", "k_w2=1:2:3", "--test", "offset", "--size", "80"], "cm"),
    (["--gain", "k_w2=1:2:3", "--test", "switch", "--formation", "blob"], "one of"),
    (["--gain", "k_w2=1:2:3", "--follower", "3"], "followers 1..2"),
])
def test_tune_refuses_bad_input_in_one_line(tmp_path, args, needle):
    r = main_cli("tune", "experiment1", *args, "--out", str(tmp_path / "o"))
    assert r.returncode == 2, r.stdout + r.stderr
    assert needle in r.stderr and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert not (tmp_path / "o").exists()  # nothing written


def test_a_test_or_sweep_with_a_follower_not_tracked_is_refused_with_the_reason(tmp_path):
    import dataclasses

    store, loop, tests, rec = _team(tmp_path)
    _tick(loop, 1.0)
    rec.close()
    assert loop.last is not None
    lost = dataclasses.replace(loop.last, tracked=np.array([True, False, True]))
    tests.on_tick(lost)  # what the runner last saw: F2 out of view
    assert tests.request(StepTest("offset", 0, 0.1)) == "F2 not tracked: a step test needs every follower in view"
    why = live_base(lost, store.get(), loop.dynamics, MeasurementNoise(), 30.0, 5)
    assert isinstance(why, str) and why.startswith("F2 not tracked")
    starting = dataclasses.replace(loop.last, phase="probe")
    tests.on_tick(starting)
    assert "start-up is not finished" in (tests.request(StepTest("offset", 0, 0.1)) or "")
    assert tests.trials == []


def test_a_turn_step_in_eq39_mode_is_refused_with_the_reason(tmp_path):
    store, loop, tests, rec = _team(tmp_path)
    store.update("browser:1", leader_mode="eq39")
    _tick(loop, 0.5)
    assert "turn step needs the leader" in (tests.request(StepTest("turn", 0, math.radians(5))) or "")
    store.update("browser:1", leader_mode="stop")
    _tick(loop, 0.5)
    assert tests.request(StepTest("turn", 0, math.radians(5), window_s=4.0)) is None
    _tick(loop, 5.0)
    assert tests.trials[-1].status == "done"
    assert store.get().leader_mode == "stop"  # set back
    rec.close()


def test_the_heat_map_shows_one_metric_in_colour_and_number_with_units():
    """Each cell's number is the metric its colour shows (not settling in colour, overshoot in
    numbers), in the colour bar's unit; the scale spans the 5th-95th percentile (one slow row does
    not flatten the rest); the ink is readable on each cell; the gains' axes carry units."""
    from core.control.tuning import GainRange, StepScore, StepTest
    from core.sim.sweep import METRICS, SweepResult
    from core.types import Gains

    from app.figures import sweep_figure

    r0, r1 = GainRange("k_w2", np.array([1.0, 2.0, 3.0])), GainRange("k_f1", np.array([0.05, 0.1]))
    scores, gains = [], []
    for i, w2 in enumerate(r0.values):
        for j, f1 in enumerate(r1.values):
            settle = 40.0 if (i, j) == (0, 0) else 2.0 + i + j  # one very slow point
            scores.append(StepScore(np.array([settle]), np.array([0.01 * (i + 1)]), np.array([0.001 * (j + 1)]),
                                    np.array([0.2]), 300))
            gains.append(Gains(k_w2=w2, k_f1=f1))
    result = SweepResult((r0, r1), StepTest("offset", 0, 0.1, "", 10.0), "truth", tuple(gains), tuple(scores), 1.0)
    for metric, (key, scale, label, decimals) in METRICS.items():
        fig = sweep_figure(result, metric=metric)
        ax = fig.axes[0]
        numbers = sorted(float(t.get_text()) for t in ax.texts)
        expected = sorted(round(s.worst[key] * scale, decimals) for s in scores)
        assert numbers == pytest.approx(expected, abs=10 ** -decimals), metric
        assert label in ax.get_title() and label in [a.get_ylabel() for a in fig.axes]  # the colour bar's unit
        assert ax.get_xlabel() == "k_w2 (1/rad)" and ax.get_ylabel() == "k_f1 (m/s)"
    fig = sweep_figure(result, metric="settling")
    lo, hi = fig.axes[0].images[0].get_clim()
    assert hi < 40.0  # the slow point does not stretch the scale


def test_a_step_test_warns_when_more_than_the_controller_moved_the_team(tmp_path):
    """The leader's motion changed during the window (an operator, the goal navigator): the
    trial is scored, and says so beside its status, in its record and on the page's table."""
    from app.live.tuning import trial_cells

    store, loop, tests, rec = _team(tmp_path)
    store.update("browser:1", safety=False)  # only the leader's change here
    _tick(loop, 3.0)
    assert tests.request(StepTest("offset", 0, 0.1, window_s=4.0)) is None
    _tick(loop, 1.0)
    store.update("browser:1", leader_speed_mps=0.01)
    _tick(loop, 4.5)
    rec.close()
    (trial,) = tests.trials
    assert trial.status == "done" and "the leader's motion changed" in trial.disturbed, trial
    assert "warning: the leader's motion changed" in trial_cells(trial)[2]
    assert trial.payload()["disturbed"] == trial.disturbed
    (tmp_path / "quiet").mkdir()
    quiet_store, quiet_loop, quiet_tests, quiet_rec = _team(tmp_path / "quiet")
    assert quiet_store.get().safety  # the filter on, as by default: it watches but moves no command here
    # the same ticks seen by two more benches: one where the filter is "active" but moves commands by
    # 0.001 m/s (no warning: 0 % is no disturbance), one where it moves them 5 cm/s on every 10th tick
    import dataclasses

    idle, acting = StepTests(quiet_store, 0.12), StepTests(quiet_store, 0.12)
    quiet_loop.subscribe(lambda st: idle.on_tick(dataclasses.replace(
        st, safety_active=np.ones(st.n, bool), safety_changed=np.full(st.n, 0.001))))
    quiet_loop.subscribe(lambda st: acting.on_tick(dataclasses.replace(
        st, safety_active=np.ones(st.n, bool), safety_changed=np.full(st.n, 0.05 if st.tick % 10 == 0 else 0.0))))
    _tick(quiet_loop, 3.0)
    assert quiet_tests.request(StepTest("offset", 0, 0.1, window_s=4.0)) is None
    assert idle.request(StepTest("offset", 1, 0.1, window_s=4.0)) is None
    assert acting.request(StepTest("offset", 2, 0.1, window_s=4.0)) is None
    _tick(quiet_loop, 5.0)
    quiet_rec.close()
    assert quiet_tests.trials[0].status == "done" and quiet_tests.trials[0].disturbed == "", quiet_tests.trials[0]
    assert idle.trials[0].status == "done" and idle.trials[0].disturbed == "", idle.trials[0]
    warn = acting.trials[0].disturbed
    assert acting.trials[0].status == "done" and "the safety filter changed commands on" in warn, warn
    import re

    part, whole, pct = re.search(r"on (\d+) of (\d+) measured ticks \(([\d.]+) %\)", warn).groups()
    assert 0 < int(part) < int(whole) and float(pct) == pytest.approx(100 * int(part) / int(whole), abs=0.5)
    from app.live.tuning import share_text

    assert [share_text(k, 300) for k in (1, 15, 150)] == ["0.3 %", "5.0 %", "50 %"]  # never "0 %" for a tick


def test_the_limits_strip_names_each_follower_and_its_time_axis():
    """Rows per follower and limit, the follower's name in its colour on the left, the seconds
    before now below; a limit active over the last seconds paints its row there."""
    import cv2

    from core.camera.render.looks import follower_rgb

    from app.dashboard.tuning_panel import (LIMIT_RGB, STRIP_AXIS_PX, STRIP_GUTTER_PX, STRIP_ROW_PX, STRIP_WIDTH,
                                            LyapunovMonitor)

    monitor = LyapunovMonitor.__new__(LyapunovMonitor)  # the drawing alone (no page needed)
    from collections import deque

    monitor._hist = deque((k / 30, np.array([1 if k >= 150 else 0, 0])) for k in range(300))  # F1's first limit, last 5 s
    img = monitor.render_strip(2)
    k = len(LIMIT_RGB)
    assert img.shape == (2 * k * STRIP_ROW_PX + STRIP_AXIS_PX, STRIP_GUTTER_PX + STRIP_WIDTH, 3)
    gutter = img[:k * STRIP_ROW_PX, :STRIP_GUTTER_PX].reshape(-1, 3)
    assert (np.abs(gutter.astype(int) - follower_rgb(0)).sum(axis=1) < 60).any()  # "F1" in F1's colour
    row = img[2, STRIP_GUTTER_PX:]
    assert (row[-10:] == LIMIT_RGB[0]).all() and (row[:100] == 255).all()  # on for the last half only
    assert (img[-STRIP_AXIS_PX:] < 200).any()  # the axis' labels
    assert cv2.imencode(".png", img)[0]
