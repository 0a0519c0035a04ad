"""A real rig's latency in the stepped simulator, and the controller's prediction over it
(core.control.prediction, the paper's odometry run forward over the commands already sent)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.config import ConfigError, Latency, parse_scenario
from core.control.prediction import predict_poses
from core.geometry import heading_world_to_leader, world_to_leader
from core.sim.stepped import simulate_stepped
from tests.helpers import SCENARIOS


def test_prediction_is_the_world_motion_seen_from_the_moving_leader():
    """Followers and leader driven in the world by their commands (unicycles, many small steps),
    then seen from the leader: the prediction in the leader frame lands where they are."""
    rng = np.random.default_rng(0)
    dt, k, n, sub = 1 / 30, 12, 3, 50
    p0 = rng.uniform(-1, 1, (n, 2))
    a0 = rng.uniform(-math.pi, math.pi, n)
    commands = np.stack([np.column_stack([rng.uniform(-0.2, 0.3, n), rng.uniform(-1, 1, n)])] * k)
    twists = np.tile([0.06, math.radians(8.0)], (k, 1))
    leader = np.array([0.0, 0.0, math.pi / 2])  # at the start the leader frame and the world agree
    xy, th = p0.copy(), a0.copy()  # world pose of each follower (heading from +x, as a is at the start)
    for j in range(k):
        for _ in range(sub):
            h = dt / sub
            v_l, w_l = twists[j]
            leader = leader + h * np.array([v_l * math.cos(leader[2]), v_l * math.sin(leader[2]), w_l])
            v, w = commands[j, :, 0], commands[j, :, 1]
            xy = xy + h * np.column_stack([v * np.cos(th), v * np.sin(th)])
            th = th + h * w
    p_true = world_to_leader(xy, leader[:2], float(leader[2]))
    a_true = np.asarray(heading_world_to_leader(th, float(leader[2])))
    p_pred, a_pred = predict_poses(p0, a0, commands, twists, dt)
    assert np.allclose(p_pred, p_true, atol=2e-3), (p_pred, p_true)
    assert np.allclose(np.angle(np.exp(1j * (a_pred - a_true))), 0.0, atol=1e-6)


def test_no_ticks_no_change_and_zero_commands_drift_back_as_the_leader_drives():
    p = np.array([[0.5, 0.3]])
    a = np.array([1.0])
    same_p, same_a = predict_poses(p, a, np.zeros((0, 1, 2)), np.zeros((0, 2)), 1 / 30)
    assert np.array_equal(same_p, p) and np.allclose(same_a, a)
    moved, _ = predict_poses(p, a, np.zeros((30, 1, 2)), np.tile([0.06, 0.0], (30, 1)), 1 / 30)
    assert np.allclose(moved, [[0.5, 0.3 - 0.06]])  # a standing robot falls behind a leader driving 1 s


@pytest.fixture(scope="module")
def experiment1():
    return parse_scenario((SCENARIOS / "experiment1.toml").read_text(), "experiment1").replace(duration_s=40.0)


def _settled_rms(scenario) -> float:
    log = simulate_stepped(scenario).log
    err = np.linalg.norm(log.error, axis=-1)[log.t > 10.0]
    return float(np.sqrt(np.mean(err ** 2)))


def test_with_600_ms_of_latency_the_prediction_keeps_the_formation_and_without_it_the_team_oscillates(experiment1):
    """360 ms camera + 240 ms radio: predicting each follower to when its command acts keeps the
    formation within 1 cm (no latency: 0.4 cm); without the prediction the heading loop rings
    (about 3 cm). The second half is what fails with --no-compensation."""
    with_ = _settled_rms(experiment1.replace(latency=Latency.split(0.6)))
    without = _settled_rms(experiment1.replace(latency=Latency.split(0.6, compensate=False)))
    print(f"\nexperiment1, 600 ms latency: formation RMS after 10 s {with_ * 100:.2f} cm compensated,"
          f" {without * 100:.2f} cm not")
    assert with_ < 0.01 and without > 2 * with_


def test_delays_are_whole_ticks_and_the_followers_hold_their_last_command(experiment1):
    """A command sent at tick k acts at tick k + radio (in ticks); in between the followers hold the
    one before: the applied commands are the sent ones, shifted."""
    from core.sim.stepped import Delays

    d = Delays(Latency(0.0, 0.1, 0.0), 1 / 30, 1, np.random.default_rng(0))
    sent = [np.array([[0.01 * k, 0.0]]) for k in range(10)]
    applied = [d.sent(c, (0.0, 0.0))[0, 0] for c in sent]
    assert d.radio == 3 and applied == pytest.approx([0.0, 0.0, 0.0] + [0.01 * k for k in range(7)])


def test_the_latency_table_is_read_and_bad_values_are_one_line():
    text = (SCENARIOS / "experiment1.toml").read_text()
    sc = parse_scenario(text + "\n[latency]\ncamera_ms = 50\nradio_ms = 30\njitter_ms = 10\ncompensate = false\n", "s")
    assert sc.latency == Latency(0.05, 0.03, 0.01, False) and sc.stepped
    assert parse_scenario(text, "s").latency == Latency() and not parse_scenario(text, "s").stepped
    for extra, words in (("camera_ms = -1", "latency.camera_ms = -1: must be a number in [0, 2000] ms"),
                         ("compensate = 1", "latency.compensate = 1: must be true or false"),
                         ("radio = 3", "latency.radio is not a known key")):
        with pytest.raises(ConfigError) as info:
            parse_scenario(text + f"\n[latency]\n{extra}\n", "s")
        assert words in str(info.value) and "\n" not in str(info.value)


def test_simulate_takes_a_latency_and_says_what_it_cost():
    from tests.helpers import main_cli

    res = main_cli("simulate", "experiment1", "--duration", "45", "--latency-ms", "100")
    assert res.returncode == 0, res.stderr
    assert "latency: camera 60 ms + radio 40 ms (jitter up to 0 ms), compensated; formation RMS from t = 22.5 s" \
        in res.stdout
    res = main_cli("simulate", "experiment1", "--latency-ms", "-5")
    assert res.returncode == 2 and "--latency-ms" in res.stderr and len(res.stderr.strip().splitlines()) <= 2
