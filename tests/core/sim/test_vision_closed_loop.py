"""Vision in the loop: simulator → synthetic frame → pipeline → controller → simulator."""


import numpy as np
import pytest

from core.camera.config import parse_camera
from core.config import parse_scenario
from core.geometry import wrap_angle
from core.sim.team import Disturbance
from core.sim.vision_run import simulate_vision

from tests.helpers import ROOT


def _camera(name):
    path = ROOT / "static_config/camera" / name
    return parse_camera(path.read_text(), name)


def _scenario(name):
    path = ROOT / "static_config/scenarios" / f"{name}.toml"
    return parse_scenario(path.read_text(), path.name).replace(rate_hz=30.0)


@pytest.fixture(scope="module")
def rig():
    return _camera("synthetic.toml")


@pytest.fixture(scope="module")
def gamma():
    return _camera("synthetic_calibrated.toml").gamma


def _steady(log, scenario, after=40.0, recovery=13.0):
    """Rows from t >= after, leaving out each disturbance and the recovery after it."""
    sel = log.t >= after
    for d in scenario.disturbances:
        sel &= ~((log.t >= d.start_s) & (log.t < d.end_s + recovery))
    return sel


@pytest.mark.parametrize("name", ["paper_simulation", "experiment1", "experiment2", "experiment3"])
def test_vision_in_the_loop_reaches_and_holds_formation(rig, gamma, name):
    scenario = _scenario(name)
    run = simulate_vision(scenario, rig, gamma)
    log = run.log
    assert run.tracked[log.t >= 0].all(), "every follower tracked throughout"
    sel = _steady(log, scenario)
    pos = np.linalg.norm(log.p_meas - log.p, axis=-1)[sel]
    head = np.degrees(np.abs(wrap_angle((log.a_meas - log.a)[sel])))
    form = np.linalg.norm(log.p_d - log.p, axis=-1)[sel]
    rms = lambda e: np.sqrt((e**2).mean(axis=0))
    print(f"{name}: start-up {run.startup_s:.1f} s; position estimate RMS {rms(pos) * 100} cm,"
          f" heading RMS {rms(head)} deg, formation RMS {rms(form) * 100} cm")
    assert np.all(rms(pos) <= 0.02)
    assert np.all(rms(head) <= 3.0)
    assert np.all(rms(form) <= 0.03)


@pytest.mark.parametrize("who", [0, 1])  # the second: the search once failed on any follower but the first
def test_a_hidden_follower_is_lost_stopped_and_found_again(rig, gamma, who):
    base = _scenario("experiment1")
    scenario = base.replace(duration_s=30.0, disturbances=(Disturbance(who, 20.0, 22.0, "hidden"),))
    run = simulate_vision(scenario, rig, gamma)
    log, dt = run.log, 1 / 30
    t = log.t
    hidden = (t >= 20.0) & (t < 22.0)
    first_lost = t[(~run.tracked[:, who]) & (t >= 0)][0]
    assert 20.0 <= first_lost <= 20.2 + 1e-9, first_lost
    lost = ~run.tracked[:, who]
    assert np.all(log.commands[lost & (t >= 0), who] == 0.0), "a lost follower is commanded zero at once"
    assert run.tracked[:, 1 - who][t >= 0].all(), "the other follower continues"
    assert lost[hidden & (t >= 20.2)].all()
    back = t[(t >= 22.0) & run.tracked[:, who]][0]
    assert back <= 22.0 + 10 * dt, back
    assert run.tracked[t >= back + dt, who].all()
    # and it rejoins the formation
    assert np.linalg.norm(log.p_d[-1, who] - log.p[-1, who]) < 0.03
