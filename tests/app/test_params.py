import threading

import numpy as np
import pytest

from app.params import FORMATION_PRESETS, Params, ParamsStore, formation_preset
from core.control.presets import MIN_SPACING_M, spacing
from core.control.safety import SafetySettings


def test_gain_changes_are_validated_and_clamped_with_a_notice():
    store = ParamsStore()
    p, notices = store.update("browser:1", k_f1=0.2)
    assert p.gains.k_f1 == 0.2 and notices == ()
    p, notices = store.update("browser:1", k_f1=50.0)
    assert p.gains.k_f1 == 1.0
    assert "k_f1 = 50.0 is outside (0, 1] m/s: set to 1" in notices[0].message
    for bad in (float("nan"), float("-inf"), float("inf")):  # no value at all: refused, never clamped to a bound
        with pytest.raises(ValueError, match=r"k_f1 = .*: must be a finite number in \(0, 1\] m/s; unchanged"):
            store.update("browser:1", k_f1=bad)
        assert store.get().gains.k_f1 == 1.0
    p, notices = store.update("browser:1", k_f1=1e308)
    assert p.gains.k_f1 == 1.0 and "k_f1 = 1e+308 is outside (0, 1] m/s: set to 1" in notices[0].message
    for bad in (float("nan"), 2.5, "three"):
        with pytest.raises(ValueError, match="n_followers = .*: must be a whole number"):
            store.update("browser:1", n_followers=bad)
    with pytest.raises(ValueError, match="slots: every x and y must be a finite number"):
        store.update("browser:1", slots=[[0.0, float("nan")]])


def test_wrong_kinds_and_unknown_keys_are_refused_and_nothing_changes():
    store = ParamsStore()
    before = store.get()
    with pytest.raises(ValueError, match="k_w2 = 'fast': must be a number"):
        store.update("browser:1", k_w2="fast")
    with pytest.raises(ValueError, match="leader_mode = 'warp': must be one of stop, straight, circle, eq39"):
        store.update("browser:1", leader_mode="warp")
    with pytest.raises(ValueError, match="colour: not a parameter"):
        store.update("browser:1", colour=3)
    assert store.get() is before


def test_slot_update_clamps_to_the_visible_area():
    store = ParamsStore(Params())
    p, notices = store.update("browser:2", slot=(1, 0.3, -9.0))
    assert p.slots[1].tolist() == [0.3, -2.0]
    assert "slot 2 y" in notices[0].message


def test_one_shot_requests_count_and_are_never_lost():
    store = ParamsStore()
    for _ in range(3):
        store.update("browser:1", step_requests=1)
    assert store.get().step_requests == 3


def test_more_followers_than_slots_get_default_slots():
    store = ParamsStore(Params())
    p, _ = store.update("browser:1", n_followers=5)
    assert p.slots.shape == (5, 2)
    assert len({tuple(s) for s in p.slots.tolist()}) == 5
    p, notices = store.update("browser:1", n_followers=40)
    assert p.n_followers == 8 and notices


def test_listeners_know_who_changed_what():
    store = ParamsStore()
    seen = []
    store.subscribe(lambda p, source, notices: seen.append((source, p.gains.k_w1)))
    store.update("browser:7", k_w1=0.9)
    store.update("server", k_w1=0.8)
    assert seen == [("browser:7", 0.9), ("server", 0.8)]


def test_concurrent_writers_swap_whole_snapshots():
    store = ParamsStore()
    errors = []

    def writer(k: int) -> None:
        for _ in range(200):
            store.update(f"browser:{k}", k_f1=0.01 + 0.001 * k, a=0.02 + 0.001 * k)

    def reader() -> None:
        for _ in range(2000):
            p = store.get()
            # each snapshot comes from one update: k_f1 and a belong together
            if p.version and round((p.gains.k_f1 - 0.01) * 1000) != round((p.gains.a - 0.02) * 1000):
                errors.append(p)

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(4)] + [threading.Thread(target=reader)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert store.get().version == 800


@pytest.mark.parametrize("name", FORMATION_PRESETS)
@pytest.mark.parametrize("n", [1, 2, 3, 6, 8])
def test_presets_give_distinct_slots_inside_the_area(name, n):
    s = formation_preset(name, n)
    assert s.shape == (n, 2)
    assert np.all(np.abs(s) <= 2.0)
    assert len({tuple(np.round(r, 6)) for r in s.tolist()}) == n
    assert np.all(np.hypot(s[:, 0], s[:, 1]) >= 0.3)  # outside the leader's body / blind centre
    # a settled team leaves the safety filter (0.25 m by default) inactive
    assert spacing(s) >= MIN_SPACING_M > SafetySettings().min_distance_m


@pytest.mark.parametrize("field, bound, toml_old, toml_new", [
    ("safety_distance_m", "SAFETY_DISTANCE", "min_distance_m = 0.25", "min_distance_m = {v}"),
    ("min_scale", "MIN_SCALE", "min_scale = 0.6", "min_scale = {v}"),
    ("leader_speed_mps", "GOAL_SPEED", "speed_mps = 0.08", "speed_mps = {v}"),
])
def test_each_bound_is_declared_once_and_the_scenario_the_store_and_params_agree(field, bound, toml_old, toml_new):
    """The scenario reader refuses what the store clamps and ``Params`` refuses, at the same
    edge, with the same range in its line (core.bounds is the one declaration)."""
    from app.files import resolve_scenario_path
    from app.services.live import params_for
    from core import bounds
    from core.config import ConfigError, parse_scenario

    b = getattr(bounds, bound)
    text = resolve_scenario_path("obstacle_course").read_text()
    assert toml_old in text
    outside = b.hi + 0.05
    with pytest.raises(ConfigError, match=rf"= {outside:g}: must be a number in [\[(]{b.lo:g}, {b.hi:g}\]"):
        parse_scenario(text.replace(toml_old, toml_new.format(v=outside)), "edge.toml")
    at_edge = parse_scenario(text.replace(toml_old, toml_new.format(v=b.hi)), "edge.toml")
    assert getattr(params_for(at_edge, at_edge.n), field) == b.hi  # a scenario's starting values are valid Params
    with pytest.raises(ValueError, match=rf"{field} = {outside!r}: must be a number in"):
        Params(**{field: outside})
    store = ParamsStore()
    p, notices = store.update("bus", **{field: outside})
    assert getattr(p, field) == b.hi and notices  # the page and the bus: clamped to the same edge, and said


def test_params_refuses_what_no_control_can_hold():
    for bad in ({"n_followers": 0}, {"n_followers": 9}, {"slots": np.array([[0.0, 2.5]])}, {"goal": (11.0, 0.0)},
                {"leader_mode": "warp"}, {"leader_turn_deg_s": 31.0}, {"safety_distance_m": 0.1}):
        with pytest.raises(ValueError):
            Params(**bad)
